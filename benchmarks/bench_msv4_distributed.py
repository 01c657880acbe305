"""``hitops calibrate REF.ps TGT.ps --scheduler`` against one process and the zarr floor (issue 37).

A hitops.testing pair (8 stations, RR LL, one channel, time order) converted by
xradio 1.3 in time chunks of ``--chunk-rows`` rows; ``hitops calibrate --method
pwc,cfpt,cwu --no-verdict`` as a process of its own: without ``--scheduler`` (this
process's threads), and with a dask LocalCluster of 1 and of 2 single-threaded worker
processes started here (a fresh cluster per configuration).  Median wall time of
``--repeats`` runs, the client's peak RSS and each worker's (``ru_maxrss`` read on
the workers after the runs); beside them the zarr floor of the same variables
(benchmarks/bench_msv4.py ``_run_floor``) and the load average before each
configuration (the machine is shared).

What the cluster runs: each chunk read, tracked, transferred and written by tasks on
the workers (hitops/calibrate/worker_chunks.py; docs/msv4.md, "Distributed"); the
client plans and commits.  The table of stage timings is the last run's report: on a
cluster its read, transfer and write are the workers' seconds summed (they overlap).

The floor is measured twice: as a process of its own (python started, numpy and zarr
imported, every partition of both bands read, one VISIBILITY and FLAG per method
written in the store's chunks: what a run's process pays too; the "x floor" column) and
inside this warm process (no start, no imports; benchmarks/bench_msv4.py).

``--n-chan N`` (N > 1): the wideband pair in place of the one-channel pair: hitops's
``wideband`` scene (5 stations; 86 GHz in one window, 230 GHz in two: two partitions)
with N channels per window, ``--integration`` and ``--duration`` setting its rows; a
section of its own.

``--reference-table``: the table path on the wideband pair.  Its 86 GHz set stays a
Measurement Set v2 and is solved by CASA fringefit (``--solint``, the wideband
recipe's reference antennas); ``hitops calibrate REF.ms TGT.ps --reference-table
REF.fringe --method pwc,cfpt``.  On a cluster each chunk is one task that reads,
corrects and writes it (hitops/calibrate/table_workers.py); the floor reads the target
alone (no reference visibilities are read).

Run: ``python -m benchmarks.bench_msv4_distributed [--n-time N] [--repeats N]
[--n-chan N --integration S --duration S] [--reference-table --solint S]
[--workdir DIR]``; writes its section of docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import dask

from ._report import machine_line, replace_section, run_process
from .bench_msv4 import METHODS, N_ANT, _convert, _run_floor, _run_floor_process


def _worker_peak_mb(client) -> list:
    # VmHWM, the peak of this address space: ru_maxrss is kept across exec, so a spawned
    # worker's would be this (benchmark) process's peak when it was forked
    def peak():
        with open("/proc/self/status") as status:
            kb = next(line.split()[1] for line in status if line.startswith("VmHWM:"))
        return int(kb) / 1024.0
    return sorted(client.run(peak).values())


def _runs(ref: Path, tgt: Path, chunk_rows: int, repeats: int, n_workers: int,
          methods: str = METHODS, table: Optional[Path] = None) -> dict:
    """``repeats`` runs, with a fresh LocalCluster of ``n_workers`` processes (0: none);
    ``table``: from that reference table (the table path)."""
    hitops = Path(sys.executable).with_name("hitops")
    load = os.getloadavg()[0]
    cluster = client = None
    extra = []
    # dask's scratch space (the scheduler's and the workers') in the benchmark's directory,
    # not the machine's /tmp
    scratch = dask.config.set({"temporary-directory": str(tgt.parent)})
    if n_workers:
        from distributed import Client, LocalCluster
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
        extra = ["--scheduler", cluster.scheduler_address]
    try:
        walls, rss = [], []
        for k in range(repeats):
            r = run_process([hitops, "calibrate", ref, tgt, "--method", methods,
                             "--chunk-rows", str(chunk_rows), "--no-verdict", "--overwrite"]
                            + (["--reference-table", table] if table else []) + extra)
            walls.append(r["wall_s"])
            rss.append(r["peak_rss_mb"])
        workers = _worker_peak_mb(client) if client else []
        report = json.loads(Path(f"{tgt}.hitops-calibrate.json").read_text())
    finally:
        if client:
            client.close()
            cluster.close()
        scratch.__exit__(None, None, None)
    return {"wall": statistics.median(walls), "walls": walls, "client_rss": max(rss),
            "workers_rss": workers, "load": load, "stages": report.get("timings_s", {})}


@dataclass(frozen=True)
class Wideband:
    """The wideband pair: hitops's ``wideband`` scene (5 stations; 86 GHz in one window,
    230 GHz in two) with ``n_chan`` channels per window and one integration every
    ``integration`` seconds over ``duration`` seconds."""

    n_chan: int
    integration: float
    duration: float


def _one_channel_pair(work: Path, n_time: int, chunk_rows: int):
    """(ref, target processing set, its description): the hitops.testing pair."""
    from hitops.testing import PairSpec, make_pair
    from hitops.testing.pairs import Storage

    pair = make_pair(work / "pair", PairSpec(n_ant=N_ANT, n_time=n_time,
                                            storage=Storage(time_order=True)))
    step = max(1, chunk_rows // (N_ANT * (N_ANT - 1) // 2))
    ref_ps, tgt_ps = work / "ref.ps.zarr", work / "tgt.ps.zarr"
    _convert(pair.ref_ms, ref_ps, "arcae", step)
    _convert(pair.target_ms, tgt_ps, "arcae", step)
    n_row = n_time * N_ANT * (N_ANT - 1) // 2
    return ref_ps, tgt_ps, (f"{n_row:,} rows per band ({N_ANT} stations, RR LL, one "
                            f"channel), converted in time chunks of {step} steps")


def _wideband_pair(work: Path, wide: Wideband, chunk_rows: int, solint: str = ""):
    """(ref, target processing set, its description): the wideband scene simulated as
    MSv2 sets and converted as the one-channel pair is (time chunks of ``chunk_rows``).
    ``solint``: the reference band is left a v2 set and its fringefit table made
    (``REF.fringe`` beside it): (ref v2, target processing set, description)."""
    from hitops.io.read import row_count
    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    scene = load_scene_mapping("wideband")[0]
    scene["observation"].update(duration=wide.duration, integration=wide.integration)
    for band in scene["bands"]:
        band["n_chan"] = wide.n_chan
    n_station = len(scene["stations"])
    step = max(1, chunk_rows // (n_station * (n_station - 1) // 2))
    sets = simulate(scene, work / "sim", overwrite=True)
    ref_ps, tgt_ps = work / "ref.ps.zarr", work / "tgt.ps.zarr"
    if solint:
        from hitops.casa.tasks import fringefit
        ref_ps = Path(sets["86"])
        fringefit(str(ref_ps), str(ref_ps.with_suffix(".fringe")), solint=solint,
                  refant="PV,PB,AP,GL,KP", minsnr=3.0, overwrite=True)
    else:
        _convert(sets["86"], ref_ps, "arcae", step)
    _convert(sets["230"], tgt_ps, "arcae", step)
    rows = [row_count(str(ps)) for ps in (ref_ps, tgt_ps)]
    return ref_ps, tgt_ps, (
        f"the wideband scene ({n_station} stations, RR LL, {wide.duration:g} s of "
        f"{wide.integration:g} s): 86 GHz {rows[0]:,} rows in one window, 230 GHz "
        f"{rows[1]:,} rows in two windows, {wide.n_chan} channels each, converted in time "
        f"chunks of {step} steps")


def bench(work: Path, n_time: int, chunk_rows: int, repeats: int,
          wideband: Optional[Wideband] = None, solint: str = "") -> str:
    """``solint``: the table path (``--reference-table``) on the wideband pair."""
    if wideband is None:
        ref_ps, tgt_ps, pair_text = _one_channel_pair(work, n_time, chunk_rows)
    else:
        ref_ps, tgt_ps, pair_text = _wideband_pair(work, wideband, chunk_rows, solint)
    table = ref_ps.with_suffix(".fringe") if solint else None
    methods = "pwc,cfpt" if table else METHODS
    n_methods = len(methods.split(","))
    read_ref = None if table else ref_ps      # the table path reads no reference band
    floor = _run_floor(read_ref, tgt_ps, n_methods, repeats)
    floor_process = _run_floor_process(read_ref, tgt_ps, n_methods, repeats)
    configs = {"one process (threads)": 0, "LocalCluster, 1 worker process": 1,
               "LocalCluster, 2 worker processes": 2}
    results = {name: _runs(ref_ps, tgt_ps, chunk_rows, repeats, n, methods, table)
               for name, n in configs.items()}
    floor_s = floor_process["wall"]
    command = (f"`hitops calibrate REF.ms TGT.ps.zarr --reference-table REF.fringe "
               f"(fringefit, solint {solint}) --method {methods}" if table else
               f"`hitops calibrate --method {methods}")
    read = "the target's" if table else "both bands'"
    lines = [
        f"Measured {time.strftime('%Y-%m-%d %H:%M')} on {machine_line()} (the load average "
        f"before each configuration given per row); {pair_text}; "
        f"{command} --chunk-rows {chunk_rows} --no-verdict "
        f"--overwrite`, each run a process of its own, median of {repeats}.  x floor: "
        "against the floor as a process of its own (python started, numpy and zarr "
        f"imported, {read} variables read, the groups written), which a run pays too.",
        "",
        "| configuration | wall s (median; all) | x floor (process) | client peak RSS MB | "
        "worker peak RSS MB | load before |",
        "|---|---|---|---|---|---|",
        f"| zarr floor, a process of its own: python + numpy + zarr imports, {read} "
        f"EFFECTIVE_INTEGRATION_TIME, VISIBILITY, FLAG read, one VISIBILITY + FLAG per "
        f"method written ({n_methods} groups) | {floor_s:.2f} "
        f"({', '.join(f'{w:.2f}' for w in floor_process['walls'])}) | 1.00 | "
        f"{floor_process['rss']:.0f} | | |",
        f"| zarr floor in a warm process (read {floor['read']:.2f} s + write "
        f"{floor['write']:.2f} s; no start, no imports) | {floor['read'] + floor['write']:.2f} | "
        f"{(floor['read'] + floor['write']) / floor_s:.2f} | | | |",
    ]
    for name, r in results.items():
        lines.append(f"| {name} | {r['wall']:.2f} ({', '.join(f'{w:.2f}' for w in r['walls'])})"
                     f" | {r['wall'] / floor_s:.2f} | {r['client_rss']:.0f} | "
                     f"{', '.join(f'{m:.0f}' for m in r['workers_rss']) or '-'} | "
                     f"{r['load']:.2f} |")
    stages = list(dict.fromkeys(k for r in results.values() for k in r["stages"]))
    lines += ["", "| the last run's stage timings, s | " + " | ".join(stages) + " |",
              "|---|" + "---|" * len(stages)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(
            f"{r['stages'][k]:.2f}" if k in r["stages"] else "" for k in stages) + " |")
    (work / "results.json").write_text(json.dumps(
        {"floor": floor, "floor_process": floor_process, "runs": results}, indent=1))
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--n-time", type=int, default=35_715)   # x 28 baselines = 10^6 rows
    parser.add_argument("--chunk-rows", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--n-chan", type=int, default=1,
                        help="channels per window; > 1: the wideband scene's pair "
                             "(--integration, --duration) in place of the one-channel pair")
    parser.add_argument("--integration", type=float, default=2.0,
                        help="wideband pair: seconds per integration (the scene's: 2)")
    parser.add_argument("--duration", type=float, default=3600.0,
                        help="wideband pair: seconds observed (the scene's: 3600)")
    parser.add_argument("--reference-table", action="store_true",
                        help="the table path on the wideband pair (--n-chan 16 unless given): "
                             "its 86 GHz set solved by CASA fringefit (--solint)")
    parser.add_argument("--solint", default="20s",
                        help="--reference-table: fringefit's solution interval")
    args = parser.parse_args(argv)
    if args.reference_table and args.n_chan == 1:
        args.n_chan = 16
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-msv4-dist-"))
    work.mkdir(parents=True, exist_ok=True)
    wideband = None
    if args.n_chan > 1:
        wideband = Wideband(args.n_chan, args.integration, args.duration)
        key = (f"msv4-distributed-{'table' if args.reference_table else 'wideband'}-"
               f"{args.n_chan}ch-{args.integration:g}s-{args.duration:g}s")
    else:
        # another size: a section of its own after the default one's
        key = "msv4-distributed" if args.n_time == 35_715 else \
            f"msv4-distributed-{args.n_time}"
    text = bench(work, args.n_time, args.chunk_rows, args.repeats, wideband,
                 args.solint if args.reference_table else "")
    replace_section(key, text)
    print(text)
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
