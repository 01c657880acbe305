"""MSv4 processing sets: conversion, store layout and the zarr read/write floor (issue 37).

On a hitops.testing pair's target set of 10^6 rows (8 stations, 28 baselines x
35,715 one-second integrations, RR LL, one channel, stored in time order as
correlators write), page cache warm:

* conversion by xradio 1.3 (``convert_msv2_to_processing_set``, defaults), each in a
  process of its own: its default casacore backend arcae, and python-casacore
  (``XRADIO_CASACORE_BACKEND=casacore``, which xradio calls an unsupported testing hook);
  wall time and peak RSS;
* the store's layout: partitions, the chunk shape of VISIBILITY, bytes on disk per
  variable against the v2 set's table files;
* the floor of the variables a calibration reads and writes: zarr reading
  EFFECTIVE_INTEGRATION_TIME, VISIBILITY and FLAG whole, and writing a new
  correlated-data and flag array of the same shape, chunks and codecs; beside it
  hitops's :class:`~hitops.io.msv4.PartitionReader` (10^5-row chunks, rows in MSv2
  terms) and :class:`~hitops.io.msv4.DataGroupWriter` (stage, write per chunk,
  register), and python-casacore's getcol of TIME, ANTENNA1, ANTENNA2, DATA, FLAG
  of the v2 set for scale.  Median of ``--repeats`` runs each.

With ``--only calibrate`` (or in a whole run, after the above): ``hitops calibrate``
on a pair of processing sets (both bands 10^6 rows, converted in time chunks of
10^5 rows) with ``--method pwc,cfpt,cwu --chunk-rows 100000 --no-verdict``, each
run a process of its own (wall, peak RSS, the report's stage timings), against
the zarr floor of the same variables (both bands' EFFECTIVE_INTEGRATION_TIME,
VISIBILITY and FLAG read whole, one VISIBILITY and FLAG array per method written
whole), measured twice: in this warm process, and as a process of its own (python
started, numpy and zarr imported: what a run's process pays too), and the same run on
the v2 sets.

Writes its sections of docs/msv4.md.  Run: ``python -m benchmarks.bench_msv4
[--workdir DIR] [--repeats N] [--only calibrate]`` (about two minutes here; no more
than 10^6 rows: the machine is shared).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

from ._report import ROOT, load_line, machine_line, replace_section, run_process

N_ANT = 8
N_TIME = 35_715            # x 28 baselines = 1,000,020 rows
CHUNK_ROWS = 100_000
DOC = ROOT / "docs" / "msv4.md"

_CONVERT = """
import json, logging, sys
logging.getLogger("toolviper").setLevel(logging.WARNING)
from xradio.measurement_set import convert_msv2_to_processing_set
convert_msv2_to_processing_set(sys.argv[1], sys.argv[2], main_chunksize=json.loads(sys.argv[3]))
"""


def _timed(fn, repeats: int) -> float:
    fn()                                       # warm: page cache, first-call costs
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs)


def _du(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def _convert(ms: Path, out: Path, backend: str, time_chunk=None) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    env = {"XRADIO_CASACORE_BACKEND": backend}
    chunks = json.dumps(None if time_chunk is None else {"time": time_chunk})
    return run_process([sys.executable, "-c", _CONVERT, str(ms), str(out), chunks], env=env)


def _zarr_floor(ps: Path, partition: str, repeats: int) -> dict:
    import zarr

    from hitops.io.msv4.store import quiet_zarr

    with quiet_zarr():
        group = zarr.open_group(str(ps), path=partition, mode="r+", use_consolidated=False)

    def read():
        return [group[v][...] for v in ("EFFECTIVE_INTEGRATION_TIME", "VISIBILITY", "FLAG")]

    vis, flag = group["VISIBILITY"][...], group["FLAG"][...]

    runs = iter(range(1000))

    def write():    # new arrays each run, as a new data group is
        k = next(runs)
        for name, like, values in ((f"FLOOR_VIS{k}", "VISIBILITY", vis),
                                   (f"FLOOR_FLAG{k}", "FLAG", flag)):
            source = group[like]
            out = group.create_array(name, shape=source.shape, dtype=source.dtype,
                                     chunks=source.chunks, compressors=source.compressors)
            out[...] = values

    with quiet_zarr():
        return {"read": _timed(read, repeats), "write": _timed(write, repeats)}


def _hitops_path(ps: Path, partition: str, repeats: int) -> dict:
    from hitops.io.msv4 import DataGroupWriter, PartitionReader, open_store, read_layout

    layout = read_layout(open_store(str(ps)))
    reader = PartitionReader(layout, partition)

    def read():
        return [c.n_row for c in reader.chunks(CHUNK_ROWS)]

    runs = iter(range(1000))

    def read_write():   # a new group each run (removing an old one's files is not measured)
        with DataGroupWriter(str(ps), partition, f"bench{next(runs)}",
                             time_chunk=reader.time_step(CHUNK_ROWS)) as writer:
            for rows in reader.chunks(CHUNK_ROWS):
                writer.write(rows, rows.data, rows.flag)

    return {"read": _timed(read, repeats), "read_write": _timed(read_write, repeats)}


def _casacore_read(ms: Path, repeats: int) -> float:
    from hitops.io import tables

    return _timed(lambda: tables.read_columns(str(ms), ["TIME", "ANTENNA1", "ANTENNA2", "DATA",
                                                          "FLAG"]), repeats)


def _layout_rows(ps: Path, ms: Path, partition: str):
    import zarr

    from hitops.io.msv4.store import quiet_zarr

    with quiet_zarr():
        group = zarr.open_group(str(ps), path=partition, mode="r")
        chunks = group["VISIBILITY"].chunks
        shape = group["VISIBILITY"].shape
    sizes = {v: _du(ps / partition / v) for v in ("VISIBILITY", "FLAG", "WEIGHT", "UVW",
                                                     "TIME_CENTROID", "EFFECTIVE_INTEGRATION_TIME")}
    return shape, chunks, sizes, _du(ps), _du(ms)


def _markdown(n_row, conv, layout, floor, mine, chunked, chunked_floor, casacore_s,
              step) -> str:
    shape, chunks, sizes, ps_bytes, ms_bytes = layout
    mb = 1e6
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {machine_line()} ({load_line()}), "
        f"xradio 1.3.0, zarr 3.1; a hitops.testing target set of {n_row:,} rows ({N_ANT} "
        "stations, RR LL, one channel, time order); page cache warm; median of the repeats.",
        "",
        "| conversion (`convert_msv2_to_processing_set`, defaults) | wall s | peak RSS MB |",
        "|---|---|---|"]
    for backend, stats in conv.items():
        lines.append(f"| {backend} | {stats['wall_s']:.1f} | {stats['peak_rss_mb']:.0f} |")
    lines += [
        "",
        f"Store: one partition, VISIBILITY {shape} in chunks of {chunks} "
        f"(time, baseline_id, frequency, polarization), blosc-lz4; {ps_bytes / mb:.0f} MB on disk "
        f"against {ms_bytes / mb:.0f} MB for the v2 set.  Per variable: "
        + ", ".join(f"{k} {v / mb:.1f} MB" for k, v in sizes.items()) + ".",
        "",
        f"| I/O of the variables a calibration reads and writes, s | store as converted "
        f"(one chunk) | converted with time chunks of {step} ({CHUNK_ROWS:,} rows) |",
        "|---|---|---|",
        f"| zarr floor: read EFFECTIVE_INTEGRATION_TIME, VISIBILITY, FLAG whole | "
        f"{floor['read']:.2f} | {chunked_floor['read']:.2f} |",
        f"| zarr floor: write a VISIBILITY and a FLAG array whole (the store's chunks, codecs) | "
        f"{floor['write']:.2f} | {chunked_floor['write']:.2f} |",
        f"| hitops PartitionReader, {CHUNK_ROWS:,}-row chunks, rows in MSv2 terms | "
        f"{mine['read']:.2f} | {chunked['read']:.2f} |",
        f"| hitops read + DataGroupWriter (stage, write per chunk in {step}-step chunks, "
        f"register) | {mine['read_write']:.2f} | {chunked['read_write']:.2f} |",
        f"| v2 for scale: python-casacore getcol TIME, ANTENNA1, ANTENNA2, DATA, FLAG | "
        f"{casacore_s:.2f} | |",
    ]
    return "\n".join(lines)


METHODS = "pwc,cfpt,cwu"
_IMPORTS = ("import zarr, hitops.calibrate.api, hitops.calibrate.plan, "
            "hitops.calibrate.pipeline, hitops.cli")


def _partitions(ps: Path) -> list:
    """The partitions of processing set ``ps`` (its child groups), in name order."""
    return sorted(p.name for p in ps.iterdir() if (p / "zarr.json").is_file())


def _run_floor(ref_ps: Optional[Path], tgt_ps: Path, n_methods: int, repeats: int) -> dict:
    """The zarr floor of a calibration's variables, in this (warm) process: every
    partition of both bands read (of the target alone when ``ref_ps`` is None: the
    ``--reference-table`` path reads no reference visibilities), the outputs written (one
    VISIBILITY and FLAG per method and target partition, whole, in the store's chunks)."""
    import zarr

    from hitops.io.msv4.store import quiet_zarr

    bands = (tgt_ps,) if ref_ps is None else (ref_ps, tgt_ps)
    with quiet_zarr(), _floor_arrays_removed(tgt_ps):
        groups = [zarr.open_group(str(ps), path=name, mode="r+", use_consolidated=False)
                  for ps in bands for name in _partitions(ps)]
        read_s = _timed(lambda: [g[v][...] for g in groups for v in
                                 ("EFFECTIVE_INTEGRATION_TIME", "VISIBILITY", "FLAG")], repeats)
        targets = groups[len(groups) - len(_partitions(tgt_ps)):]
        values = [(g, g["VISIBILITY"][...], g["FLAG"][...]) for g in targets]
        runs = iter(range(1000))

        def write():
            k = next(runs)
            for target, vis, flag in values:
                for m in range(n_methods):
                    for name, like, array in ((f"FLOOR_VIS{k}_{m}", "VISIBILITY", vis),
                                              (f"FLOOR_FLAG{k}_{m}", "FLAG", flag)):
                        source = target[like]
                        target.create_array(name, shape=source.shape, dtype=source.dtype,
                                            chunks=source.chunks,
                                            compressors=source.compressors)[...] = array
        write_s = _timed(write, repeats)
    return {"read": read_s, "write": write_s}


#: the floor as a process of its own: what a run pays besides its kernels and bookkeeping
#: (python's start, numpy's and zarr's imports, every partition of both bands read, one
#: VISIBILITY and FLAG per method and target partition written in the store's chunks)
_FLOOR_PROCESS = """
import sys, warnings
from pathlib import Path
import numpy, zarr
warnings.filterwarnings("ignore")
ref, tgt, n_methods, tag = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
def partitions(ps):
    return sorted(p.name for p in ps.iterdir() if (p / "zarr.json").is_file())
outputs = []
for ps in ((tgt,) if str(ref) == "-" else (ref, tgt)):
    for name in partitions(ps):
        group = zarr.open_group(str(ps), path=name, mode="r+", use_consolidated=False)
        arrays = {v: group[v][...] for v in ("EFFECTIVE_INTEGRATION_TIME", "VISIBILITY", "FLAG")}
        if ps == tgt:
            outputs.append((group, arrays))
for group, arrays in outputs:
    for m in range(n_methods):
        for like in ("VISIBILITY", "FLAG"):
            source = group[like]
            group.create_array(f"FLOOR_{tag}_{like}_{m}", shape=source.shape, dtype=source.dtype,
                               chunks=source.chunks, compressors=source.compressors
                               )[...] = arrays[like]
"""


def _run_floor_process(ref_ps: Optional[Path], tgt_ps: Path, n_methods: int,
                       repeats: int) -> dict:
    """The floor as a process of its own (:data:`_FLOOR_PROCESS`; the target alone when
    ``ref_ps`` is None): median wall and the largest peak RSS of ``repeats`` runs; the
    arrays it wrote are removed after each."""
    runs = []
    for k in range(repeats):
        with _floor_arrays_removed(tgt_ps):
            runs.append(run_process([sys.executable, "-c", _FLOOR_PROCESS,
                                     "-" if ref_ps is None else ref_ps, tgt_ps,
                                     n_methods, f"P{k}"]))
    return {"wall": statistics.median(r["wall_s"] for r in runs),
            "walls": [r["wall_s"] for r in runs], "rss": max(r["peak_rss_mb"] for r in runs)}


@contextlib.contextmanager
def _floor_arrays_removed(ps: Path):
    """The floors' arrays off the store again on exit: their files removed and the
    root's and partitions' zarr.json (zarr lists a new array in its group's consolidated
    metadata) put back as they were, so that the runs after see the store as converted."""
    documents = [ps / "zarr.json"] + [ps / name / "zarr.json" for name in _partitions(ps)]
    before = {doc: doc.read_bytes() for doc in documents}
    try:
        yield
    finally:
        for name in _partitions(ps):
            for array in (ps / name).glob("FLOOR_*"):
                shutil.rmtree(array)
        for doc, text in before.items():
            doc.write_bytes(text)


def _calibrate_runs(ref: Path, tgt: Path, repeats: int) -> dict:
    """``hitops calibrate`` as its own process, ``repeats`` times (--overwrite after the
    first): the median wall time, the largest peak RSS, the last report's timings."""
    hitops = Path(sys.executable).with_name("hitops")
    report = tgt.parent / f"{tgt.name}.bench.json"
    runs = []
    for k in range(repeats):
        runs.append(run_process([hitops, "calibrate", ref, tgt, "--method", METHODS,
                                 "--chunk-rows", str(CHUNK_ROWS), "--no-verdict",
                                 "--report", report] + (["--overwrite"] if k else [])))
    timings = json.loads(report.read_text()).get("timings_s", {})
    return {"wall": statistics.median(r["wall_s"] for r in runs),
            "rss": max(r["peak_rss_mb"] for r in runs), "timings": timings}


def bench_calibrate(work: Path, repeats: int) -> str:
    """The calibrate section: a v4 run against its zarr floor and against the v2 run."""
    from hitops.testing import PairSpec, make_pair
    from hitops.testing.pairs import Storage

    pair = make_pair(work / "cal-pair", PairSpec(n_ant=N_ANT, n_time=N_TIME,
                                                storage=Storage(time_order=True)))
    step = CHUNK_ROWS // (N_ANT * (N_ANT - 1) // 2)
    ref_ps, tgt_ps = work / "cal-ref.ps.zarr", work / "cal-tgt.ps.zarr"
    _convert(pair.ref_ms, ref_ps, "arcae", step)
    _convert(pair.target_ms, tgt_ps, "arcae", step)
    floor = _run_floor(ref_ps, tgt_ps, len(METHODS.split(",")), repeats)
    floor_process = _run_floor_process(ref_ps, tgt_ps, len(METHODS.split(",")), repeats)
    # what every run's process spends before its first stage: python, numpy, numba, dask,
    # zarr and hitops's calibrate modules imported
    imports = statistics.median(run_process([sys.executable, "-c", _IMPORTS])["wall_s"]
                                for _ in range(repeats))
    v4 = _calibrate_runs(ref_ps, tgt_ps, repeats)
    v2 = _calibrate_runs(pair.ref_ms, pair.target_ms, repeats)
    n_row = N_TIME * N_ANT * (N_ANT - 1) // 2
    floor_s = floor["read"] + floor["write"]
    stages = ("checks", "open", "metadata", "match", "read", "track", "transfer", "write")

    def stage_cells(t):
        return " | ".join(f"{t[k]:.2f}" if k in t else "" for k in stages)

    return "\n".join([
        f"Measured {time.strftime('%Y-%m-%d')} on {machine_line()} ({load_line()}); "
        f"a hitops.testing pair of {n_row:,} rows per band ({N_ANT} stations, RR LL, one "
        f"channel, time order), converted by xradio 1.3 in time chunks of {step} steps "
        f"({CHUNK_ROWS:,} rows); `hitops calibrate --method {METHODS} --chunk-rows "
        f"{CHUNK_ROWS} --no-verdict`, each run a process of its own (median of {repeats}; "
        "runs after the first with --overwrite); page cache warm.",
        "",
        "| | wall s | peak RSS MB |",
        "|---|---|---|",
        f"| zarr floor in this warm process (no start, no imports): both bands' "
        f"EFFECTIVE_INTEGRATION_TIME, VISIBILITY, FLAG read whole ({floor['read']:.2f} s) + one "
        f"VISIBILITY and FLAG per method written whole ({floor['write']:.2f} s) | {floor_s:.2f} "
        "| |",
        f"| zarr floor as a process of its own (python started, numpy and zarr imported, "
        f"the same reads and writes), which a run pays too | {floor_process['wall']:.2f} | "
        f"{floor_process['rss']:.0f} |",
        f"| the imports alone (python, numpy, numba, dask, zarr, hitops's calibrate modules) | "
        f"{imports:.2f} | |",
        f"| `hitops calibrate` on the processing sets | {v4['wall']:.2f} | {v4['rss']:.0f} |",
        f"| `hitops calibrate` on the v2 sets, for scale | {v2['wall']:.2f} | {v2['rss']:.0f} |",
        "",
        "| the run's stage timings (its report), s | " + " | ".join(stages) + " |",
        "|---|" + "---|" * len(stages),
        "| processing sets | " + stage_cells(v4["timings"]) + " |",
        "| v2 sets | " + stage_cells(v2["timings"]) + " |",
    ])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", choices=["calibrate"], default=None)
    args = parser.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-msv4-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.only != "calibrate":
        _bench_io(work, args.repeats)
    text = bench_calibrate(work, args.repeats)
    replace_section("msv4-calibrate", text, DOC)
    print(text)
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


def _bench_io(work: Path, repeats: int) -> None:
    """The conversion, layout and I/O section (docs/msv4.md, bench:msv4)."""
    from hitops.testing import PairSpec, make_pair
    from hitops.testing.pairs import Storage

    pair = make_pair(work / "pair", PairSpec(n_ant=N_ANT, n_time=N_TIME,
                                            storage=Storage(time_order=True)))
    ms = pair.target_ms
    step = CHUNK_ROWS // (N_ANT * (N_ANT - 1) // 2)
    conv = {"arcae (xradio's default)": _convert(ms, work / "arcae.ps.zarr", "arcae"),
            "python-casacore (XRADIO_CASACORE_BACKEND=casacore)":
                _convert(ms, work / "casacore.ps.zarr", "casacore"),
            f"arcae, main_chunksize={{'time': {step}}}":
                _convert(ms, work / "chunked.ps.zarr", "arcae", step)}
    ps = work / "arcae.ps.zarr"
    partition = sorted(p.name for p in ps.iterdir() if p.is_dir())[0]
    layout = _layout_rows(ps, ms, partition)
    floor = _zarr_floor(ps, partition, repeats)
    mine = _hitops_path(ps, partition, repeats)
    chunked_floor = _zarr_floor(work / "chunked.ps.zarr", partition, repeats)
    chunked = _hitops_path(work / "chunked.ps.zarr", partition, repeats)
    casacore_s = _casacore_read(ms, repeats)
    text = _markdown(N_TIME * N_ANT * (N_ANT - 1) // 2, conv, layout, floor, mine, chunked,
                     chunked_floor, casacore_s, step)
    replace_section("msv4", text, DOC)
    print(text)


if __name__ == "__main__":
    main()
