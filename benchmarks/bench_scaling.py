"""Scaling of ``hitops calibrate`` and ``hitops simulate`` with rows, stations and workers (issue 7).

Every figure is a whole process (benchmarks/_report.run_process: wall, CPU,
peak RSS from the kernel's accounting); medians of ``--repeats`` runs up to
10^6 rows, one run at 10^7 (a 10^7-row pair is ~1.6 GB per band and takes
minutes to build on this 2-core machine).

calibrate (``--method pwc``) on hitops.testing.make_pair pairs,
4 correlations, one channel:

* rows: 8 stations (28 baselines), 10^4 .. 10^7 rows per band, each with the
  I/O floors of the same pair beside it (benchmarks/_floors.py) and a run with
  ``--chunk-rows 250000`` for the memory ceiling;
* stations: 4, 8, 16, 30 stations, 1 h of 1 s;
* workers: the threaded scheduler with 1 and 2 threads (``DASK_NUM_WORKERS``)
  on the 10^6-row pair (processes: benchmarks/bench_distributed.py).

simulate (both bands, RR/LL): a synthetic 30-station array within ~100 km
of the VLA site (all stations see M87 together, so rows = n_bl x n_time):

* rows: 10^4 .. 10^7 via the duration (30 stations, 435 baselines);
* stations: 4, 8, 16, 30 (``--stations``), 1 h;
* threads: ``--threads 1`` and ``2`` on the 10^6-row run.

Growth exponents: least-squares slope of log(wall) against log(rows) (or
log(stations)) over all points, and the slope between the two largest points
(the asymptotic one, once fixed start-up costs no longer dominate).

Memory ceiling (``--memory-only``, its own section ``scaling-memory``): peak
RSS of ``hitops calibrate --method pwc`` at 10^5, 10^6, 4x10^6 and 10^7 rows per
band with ``--chunk-rows 250000`` and with the default chunk, one run each.

Run: ``python -m benchmarks.bench_scaling [--workdir DIR] [--repeats N] [--max-rows N]``
or ``python -m benchmarks.bench_scaling --memory-only [--max-rows N]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ._floors import measure_floors
from ._report import PLOT_DIR, machine_line, median, replace_section, run_process, save_figure

CORRS = ("RR", "RL", "LR", "LL")
ROWS = (10_000, 100_000, 1_000_000, 10_000_000)
STATIONS = (4, 8, 16, 30)
CHUNK_ROWS = 250_000
MEMORY_ROWS = (100_000, 1_000_000, 4_000_000, 10_000_000)
VLA = (34.079, -107.618, 2100.0)


def _timed(cmd, repeats, env=None):
    runs = [run_process(cmd, env=env) for _ in range(repeats)]
    return {"wall_s": median([r["wall_s"] for r in runs]),
            "cpu_s": median([r["cpu_s"] for r in runs]),
            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs), "n": repeats,
            "runs": [r["wall_s"] for r in runs]}


def exponents(x, y):
    """(slope of the log-log least-squares fit, slope between the two largest points)."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    fit = float(np.polyfit(lx, ly, 1)[0]) if lx.size > 1 else float("nan")
    last = float((ly[-1] - ly[-2]) / (lx[-1] - lx[-2])) if lx.size > 1 else float("nan")
    return fit, last


def _itrf(lat, lon, h):
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    lat, lon = np.radians(lat), np.radians(lon)
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return [float((n + h) * np.cos(lat) * np.cos(lon)), float((n + h) * np.cos(lat) * np.sin(lon)),
            float((n * (1 - e2) + h) * np.sin(lat))]


def write_scene(path: Path, n_station: int = 30) -> Path:
    """A 30-station array around the VLA site; M87 transits there near 06:30 UTC on
    2023-04-10, so a track starting 03:15 UTC stays above 40 deg for 6.4 h."""
    import yaml

    rng = np.random.default_rng(1)
    stations = []
    for i in range(n_station):
        lat = VLA[0] + rng.uniform(-1, 1)
        lon = VLA[1] + rng.uniform(-1.2, 1.2)
        stations.append({"code": f"S{i:02d}", "name": f"SITE{i:02d}", "itrf": _itrf(lat, lon, VLA[2]),
                         "diameter": 12, "coherence_time": 10,
                         "bands": {"86": {"t_rx": 50, "aperture_efficiency": 0.6, "tau": 0.05,
                                          "t_atm": 260},
                                   "230": {"t_rx": 80, "aperture_efficiency": 0.5, "tau": 0.1,
                                           "t_atm": 260}}})
    scene = {"name": "scaling",
             "source": {"name": "M87", "ra": "12h30m49.42s", "dec": "+12d23m28.04s",
                        "flux": {"86": 1.1, "230": 1.0}},
             "observation": {"start": "2023-04-10T03:15:00", "duration": 3600, "integration": 1,
                             "correlations": ["RR", "LL"]},
             "bands": [{"name": "86", "freq_ghz": 86, "bandwidth_ghz": 2},
                       {"name": "230", "freq_ghz": 230, "bandwidth_ghz": 2}],
             "corruptions": {"troposphere": True, "noise": True, "seed": 11,
                             "coherence_freq_ghz": 230},
             "stations": stations}
    path.write_text(yaml.safe_dump(scene, sort_keys=False))
    return path


def _scene(n_ant: int, n_time: int, ref_names):
    """The calibrate points' synthetic pair: 4 correlations, weak noise, slow troposphere."""
    from hitops.testing import PairSpec, Signal, Troposphere

    return PairSpec(n_ant=n_ant, n_time=n_time, corr_types=CORRS, seed=7, ref_names=ref_names,
                    troposphere=Troposphere(step_rad=0.05, drift_rad=0.01),
                    signal=Signal(sigma_ref=0.05, sigma_target=0.1))


def _nrows(ms) -> int:
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        return t.nrows()


def calibrate_point(workdir: Path, hitops: str, n_ant: int, n_time: int, repeats: int,
                    floors: bool, chunked: bool, thread_counts=()):
    from hitops.testing import make_pair

    pair_dir = workdir / f"pair-{n_ant}-{n_time}"
    shutil.rmtree(pair_dir, ignore_errors=True)
    t0 = time.perf_counter()
    names = [f"A{i:02d}" for i in range(n_ant)]   # make_pair names at most 8 by default
    truth = make_pair(pair_dir, _scene(n_ant, n_time, names))
    build_s = time.perf_counter() - t0
    del truth
    ref, tgt = pair_dir / "ref.ms", pair_dir / "target.ms"
    cmd = [hitops, "calibrate", str(ref), str(tgt), "--method", "pwc", "--overwrite",
           "--report", str(pair_dir / "report.json")]
    out = {"n_ant": n_ant, "rows": _nrows(tgt), "build_s": build_s}
    run_process(cmd)   # warm-up: page cache, numba cache
    out["calibrate"] = _timed(cmd, repeats)
    if floors:
        out["floors"] = measure_floors(pair_dir, ref, tgt, repeats=repeats,
                                       names=("issue", "same_columns"))
    if chunked:
        out["chunked"] = _timed(cmd + ["--chunk-rows", str(CHUNK_ROWS)], 1)
    for n in thread_counts:
        out[f"threads{n}"] = _timed(cmd, repeats, env={"DASK_NUM_WORKERS": str(n)})
    shutil.rmtree(pair_dir, ignore_errors=True)
    return out


def memory_point(workdir: Path, hitops: str, rows: int):
    """Peak RSS of calibrate with --chunk-rows CHUNK_ROWS and with the default chunk."""
    import json

    from hitops.testing import make_pair

    pair_dir = workdir / f"mem-{rows}"
    shutil.rmtree(pair_dir, ignore_errors=True)
    make_pair(pair_dir, _scene(8, max(2, rows // 28), [f"A{i:02d}" for i in range(8)]))
    ref, tgt = pair_dir / "ref.ms", pair_dir / "target.ms"
    out = []
    for chunk in (CHUNK_ROWS, None):
        report_path = pair_dir / "report.json"
        cmd = [hitops, "calibrate", str(ref), str(tgt), "--method", "pwc", "--overwrite",
               "--report", str(report_path)] + (["--chunk-rows", str(chunk)] if chunk else [])
        r = run_process(cmd)
        rep = json.loads(report_path.read_text())
        out.append({"rows": _nrows(tgt), "chunk_rows": chunk, "wall_s": r["wall_s"],
                    "cpu_s": r["cpu_s"], "peak_rss_mb": r["peak_rss_mb"],
                    "chunks": rep["chunks"], "timings": rep["timings_s"]})
        print("memory", out[-1], flush=True)
    shutil.rmtree(pair_dir, ignore_errors=True)
    return out


def render_memory(points, load) -> str:
    """The ``scaling-memory`` section from memory_point results."""
    lines, by_chunk = [], {}
    for p in sorted(points, key=lambda p: (p["rows"], p["chunk_rows"] is None)):
        chunk = f"{p['chunk_rows']:,}" if p["chunk_rows"] else "default (from --memory-budget auto)"
        lines.append(f"| {p['rows']:,} | {chunk} | {p['chunks']} | {p['wall_s']:.2f} | "
                     f"{p['peak_rss_mb']:.0f} |")
        by_chunk.setdefault(p["chunk_rows"], []).append(p)
    fixed = sorted(by_chunk.get(CHUNK_ROWS, []), key=lambda p: p["rows"])
    slope = (1024 * 1024 * (fixed[-1]["peak_rss_mb"] - fixed[-2]["peak_rss_mb"])
             / (fixed[-1]["rows"] - fixed[-2]["rows"]) / 2) if len(fixed) > 1 else float("nan")
    e_rss = exponents([p["rows"] for p in fixed], [p["peak_rss_mb"] for p in fixed])
    return f"""## Memory ceiling of hitops calibrate (issue 7)

Machine: {machine_line()}; 1-minute load average {load[0]:.1f} at the start,
{load[-1]:.1f} at the end.  One whole process per cell (peak RSS from the kernel's
accounting), 8 stations, 4 correlations, hitops.testing pairs (stored
baseline by baseline, i.e. not in time order); `python -m benchmarks.bench_scaling
--memory-only`.

| rows per band | --chunk-rows | chunks | wall (s) | peak RSS (MB) |
|---|---|---|---|---|
{chr(10).join(lines)}

With --chunk-rows {CHUNK_ROWS:,} the peak grows by {slope:.0f} bytes per row per band
between the two largest tracks (peak RSS ~ rows^{e_rss[0]:.2f} over all points,
{e_rss[1]:.2f} between the two largest).  calibrate reads and matches the per-row
metadata chunk by chunk (hitops/calibrate/band_index.py, chunks.py); what stays for the whole
track is per time (the union time axis, each time's scan and row count), each row's antenna
pair (2 bytes per row and band) and the rows written (1 byte per target row).  Without a
cluster these one-group sets are read with python-casacore, a baseline-major one in time
order through hitops/io/time_sorted.py (the runs of rows of each bucket of times, a few
bytes per bucket: no sort held for the run); through dask-ms (a cluster, or sets of several
fields or windows) dask-ms also keeps its row numbers and the TaQL selection behind them
(about 37 bytes per row of both bands for a table it must sort, 21 for one in time order,
measured before issue 28).  The default chunk follows from the memory budget (1 GB here;
hitops/calibrate/memory.py): a run that fits in one chunk is read in storage order; a
larger one is cut so that its peak stays within the budget, down to a floor of 100,000
rows per chunk with a warning when the whole-run part alone leaves no room.  Several
chunks cost time: each chunk reads TIME, ROWID and FLAG_ROW beside its data (its
baselines and times, like the checks before any write, come from the index pass, which
indexes a baseline-major table in storage order and places each row in the time order),
and a baseline-major table is read in runs, one per baseline and bucket of times.
"""


ORDER_ROWS = (1_000_000, 4_000_000, 10_000_000)


def orders_point(workdir: Path, hitops: str, rows: int, time_order: bool, repeats: int):
    """``hitops calibrate REF TGT --overwrite`` (default options) and the same-columns floor,
    interleaved run by run, on one pair stored in time order or baseline by baseline."""
    import json

    from hitops.testing import make_pair
    from hitops.testing.pairs import Storage

    from ._floors import floor_commands

    pair_dir = workdir / f"order-{rows}-{'time' if time_order else 'baseline'}"
    shutil.rmtree(pair_dir, ignore_errors=True)
    spec = _scene(8, max(2, rows // 28), [f"A{i:02d}" for i in range(8)])
    make_pair(pair_dir, dataclasses.replace(spec, storage=Storage(time_order=time_order)))
    ref, tgt = pair_dir / "ref.ms", pair_dir / "target.ms"
    report_path = pair_dir / "report.json"
    cmd = [hitops, "calibrate", str(ref), str(tgt), "--overwrite", "--report", str(report_path)]
    floor = floor_commands(pair_dir, ref, tgt)["same_columns"]
    run_process(floor)   # warm-up: page cache, numba cache, the output column created
    run_process(cmd)
    runs = []
    for _ in range(repeats):
        load = os.getloadavg()[0]
        f = run_process(floor)
        c = run_process(cmd)
        rep = json.loads(report_path.read_text())
        runs.append({"load": load, "floor": f, "calibrate": c, "chunks": rep["chunks"],
                     "timings": rep["timings_s"]})
        print("orders", rows, "time" if time_order else "baseline", runs[-1], flush=True)
    out = {"rows": _nrows(tgt), "time_order": time_order, "runs": runs}
    shutil.rmtree(pair_dir, ignore_errors=True)
    return out


def render_orders(points, load) -> str:
    """The ``scaling-orders`` section from orders_point results."""
    lines = []
    for p in points:
        ratios = [r["calibrate"]["wall_s"] / r["floor"]["wall_s"] for r in p["runs"]]
        cpu_ratios = [r["calibrate"]["cpu_s"] / r["floor"]["cpu_s"] for r in p["runs"]]
        runs = "; ".join(f"{r['calibrate']['wall_s']:.2f} / {r['floor']['wall_s']:.2f} "
                         f"(CPU {r['calibrate']['cpu_s']:.2f} / {r['floor']['cpu_s']:.2f}) at "
                         f"load {r['load']:.1f}" for r in p["runs"])
        stages = ", ".join(f"{k} {v:.2f}" for k, v in p["runs"][-1]["timings"].items()
                           if isinstance(v, (int, float)) and k not in ("total",))
        lines.append(
            f"| {p['rows']:,} | {'time' if p['time_order'] else 'baseline by baseline'} | "
            f"{p['runs'][-1]['chunks']} | {runs} | {median(ratios):.2f} "
            f"({', '.join(f'{x:.2f}' for x in ratios)}) | {median(cpu_ratios):.2f} | "
            f"{max(r['calibrate']['peak_rss_mb'] for r in p['runs']):.0f} | "
            f"{max(r['floor']['peak_rss_mb'] for r in p['runs']):.0f} | {stages} |")
    return f"""## hitops calibrate at 10^6 .. 10^7 rows in both storage orders (issue 28)

Machine: {machine_line()}; 1-minute load average {load[0]:.1f} at the start and
{load[-1]:.1f} at the end, and before each pair of runs in the table (the machine is
shared by several agents: wall times carry their load).  hitops.testing pairs, 8
stations, 4 correlations, one channel, stored in time order or baseline by baseline;
`hitops calibrate REF TGT --overwrite` with default options (memory budget auto, the
verdict on) against the same-columns I/O floor (benchmarks/_floors.py: a python-casacore
process reading TIME, ANTENNA1/2, SCAN_NUMBER, INTERVAL, FLAG_ROW, DATA and FLAG of both
bands whole and writing one column), run in turn, one pair of runs after the other;
ratios run by run.  Targets (issue 28): <= 1.5x the floor in time order, <= 2x baseline
by baseline, <= 1 GB peak by default at 10^7 rows per band.
`python -m benchmarks.bench_scaling --orders [--max-rows N] [--repeats N]`.

| rows per band | storage order | chunks | calibrate / floor wall (CPU) (s), each run | wall ratio run by run: median (each) | CPU ratio, median | calibrate peak RSS (MB) | floor peak RSS (MB) | stages of the last run (s) |
|---|---|---|---|---|---|---|---|---|
{chr(10).join(lines)}
"""


def simulate_point(workdir: Path, hitops: str, scene: Path, duration: float, stations,
                   repeats: int, thread_counts=()):
    outdir = workdir / "sim"
    cmd = [hitops, "simulate", str(scene), "--outdir", str(outdir), "--prefix", "s",
           "--duration", str(duration), "--overwrite"]
    if stations:
        cmd += ["--stations", ",".join(stations)]
    out = {"n_station": len(stations) if stations else 30}
    out["simulate"] = _timed(cmd, repeats)
    out["rows"] = _nrows(outdir / "s-230.ms")
    for n in thread_counts:
        out[f"threads{n}"] = _timed(cmd + ["--threads", str(n)], repeats)
    shutil.rmtree(outdir, ignore_errors=True)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-rows", type=int, default=ROWS[-1])
    parser.add_argument("--from-json", default=None,
                        help="re-render the section from a saved scaling-results.json")
    parser.add_argument("--memory-only", action="store_true",
                        help="only the memory ceiling (section scaling-memory)")
    parser.add_argument("--memory-from-json", default=None,
                        help="re-render the memory section from a saved memory-results.json")
    parser.add_argument("--orders", action="store_true",
                        help="only calibrate against the floor at 10^6, 4x10^6 and 10^7 rows in "
                             "time order and baseline by baseline (section scaling-orders)")
    args = parser.parse_args(argv if argv is not None else [])
    if args.orders:
        import json

        workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-orders-"))
        workdir.mkdir(parents=True, exist_ok=True)
        hitops = str(Path(sys.executable).with_name("hitops"))
        load = [os.getloadavg()[0]]
        points = [orders_point(workdir, hitops, rows, time_order, args.repeats)
                  for rows in ORDER_ROWS if rows <= args.max_rows
                  for time_order in (True, False)]
        load.append(os.getloadavg()[0])
        (workdir / "orders-results.json").write_text(json.dumps(
            {"points": points, "load": load}, indent=1))
        markdown = render_orders(points, load)
        print(markdown)
        replace_section("scaling-orders", markdown)
        return
    if args.memory_from_json or args.memory_only:
        import json

        if args.memory_from_json:
            saved = json.loads(Path(args.memory_from_json).read_text())
        else:
            workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-memory-"))
            workdir.mkdir(parents=True, exist_ok=True)
            hitops = str(Path(sys.executable).with_name("hitops"))
            load = [os.getloadavg()[0]]
            points = [e for rows in MEMORY_ROWS if rows <= args.max_rows
                      for e in memory_point(workdir, hitops, rows)]
            saved = {"points": points, "load": load + [os.getloadavg()[0]]}
            (workdir / "memory-results.json").write_text(json.dumps(saved, indent=1))
        markdown = render_memory(saved["points"], saved["load"])
        print(markdown)
        replace_section("scaling-memory", markdown)
        return
    if args.from_json:
        import json

        saved = json.loads(Path(args.from_json).read_text())
        render(saved["cal_rows"], saved["cal_st"], saved["sim_rows"], saved["sim_st"],
               saved["load"], saved["total"])
        return
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-scaling-"))
    workdir.mkdir(parents=True, exist_ok=True)
    hitops = str(Path(sys.executable).with_name("hitops"))
    rows_list = [r for r in ROWS if r <= args.max_rows]
    started = time.perf_counter()
    load = [os.getloadavg()[0]]

    cal_rows = []
    for rows in rows_list:
        big = rows >= 10_000_000
        cal_rows.append(calibrate_point(
            workdir, hitops, 8, max(2, rows // 28), 1 if big else args.repeats, floors=True,
            chunked=rows >= 100_000, thread_counts=(1, 2) if rows == 1_000_000 else ()))
        print("calibrate rows", cal_rows[-1]["rows"], cal_rows[-1]["calibrate"], flush=True)
    cal_st = []
    for n_ant in STATIONS:
        cal_st.append(calibrate_point(workdir, hitops, n_ant, 3600, args.repeats, floors=False,
                                      chunked=False))
        print("calibrate stations", n_ant, cal_st[-1]["calibrate"], flush=True)
    load.append(os.getloadavg()[0])

    scene = write_scene(workdir / "scaling.yml")
    codes = [f"S{i:02d}" for i in range(30)]
    sim_rows = []
    for rows in rows_list:
        big = rows >= 10_000_000
        sim_rows.append(simulate_point(workdir, hitops, scene, max(2, rows // 435), None,
                                       1 if big else args.repeats,
                                       thread_counts=(1, 2) if rows == 1_000_000 else ()))
        print("simulate rows", sim_rows[-1]["rows"], sim_rows[-1]["simulate"], flush=True)
    sim_st = []
    for n in STATIONS:
        sim_st.append(simulate_point(workdir, hitops, scene, 3600, codes[:n], args.repeats))
        print("simulate stations", n, sim_st[-1]["simulate"], flush=True)
    load.append(os.getloadavg()[0])
    total = time.perf_counter() - started

    import json

    (workdir / "scaling-results.json").write_text(json.dumps(
        {"cal_rows": cal_rows, "cal_st": cal_st, "sim_rows": sim_rows, "sim_st": sim_st,
         "load": load, "total": total}, indent=1))
    render(cal_rows, cal_st, sim_rows, sim_st, load, total)
    if not args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)


def render(cal_rows, cal_st, sim_rows, sim_st, load, total) -> None:
    """Plot, print and write the docs section (``--from-json`` re-renders saved results)."""
    fig = plot(cal_rows, cal_st, sim_rows, sim_st, PLOT_DIR / "scaling.png")
    markdown = report(cal_rows, cal_st, sim_rows, sim_st, load, total, fig)
    print(markdown)
    replace_section("scaling", markdown)


def _cell(t):
    return f"{t['wall_s']:.2f}" + (f" (n={t['n']})" if t["n"] > 1 else " (1 run)")


def report(cal_rows, cal_st, sim_rows, sim_st, load, total, fig) -> str:
    lines = []
    for p in cal_rows:
        c, f = p["calibrate"], p["floors"]
        ch = p.get("chunked")
        lines.append(
            f"| {p['rows']:,} | {_cell(c)} | {c['cpu_s']:.2f} | {c['peak_rss_mb']:.0f} | "
            f"{f['issue']['wall_s']:.2f} | {c['wall_s'] / f['issue']['wall_s']:.1f} | "
            f"{f['same_columns']['wall_s']:.2f} | {c['wall_s'] / f['same_columns']['wall_s']:.1f} | "
            + (f"{ch['wall_s']:.2f} | {ch['peak_rss_mb']:.0f} |" if ch else "- | - |"))
    rows = [p["rows"] for p in cal_rows]
    e_wall = exponents(rows, [p["calibrate"]["wall_s"] for p in cal_rows])
    e_rss = exponents(rows, [p["calibrate"]["peak_rss_mb"] for p in cal_rows])
    chunked = [p for p in cal_rows if "chunked" in p]
    e_chunk = exponents([p["rows"] for p in chunked], [p["chunked"]["peak_rss_mb"] for p in chunked])
    per_row = (1024 * 1024 * (chunked[-1]["chunked"]["peak_rss_mb"] - chunked[-2]["chunked"]["peak_rss_mb"])
               / (chunked[-1]["rows"] - chunked[-2]["rows"])) if len(chunked) > 1 else float("nan")
    big = cal_rows[-1]
    big_ratio = big["calibrate"]["wall_s"] / big["floors"]["issue"]["wall_s"]
    st_lines = [f"| {p['n_ant']} | {p['n_ant'] * (p['n_ant'] - 1) // 2} | {p['rows']:,} | "
                f"{_cell(p['calibrate'])} | {p['calibrate']['peak_rss_mb']:.0f} |" for p in cal_st]
    e_st = exponents([p["n_ant"] for p in cal_st], [p["calibrate"]["wall_s"] for p in cal_st])
    thr = next(p for p in cal_rows if "threads1" in p) if any("threads1" in p for p in cal_rows) else None
    sim_lines = [f"| {p['rows']:,} | {_cell(p['simulate'])} | {p['simulate']['cpu_s']:.2f} | "
                 f"{p['simulate']['peak_rss_mb']:.0f} |" for p in sim_rows]
    e_sim = exponents([p["rows"] for p in sim_rows], [p["simulate"]["wall_s"] for p in sim_rows])
    e_sim_rss = exponents([p["rows"] for p in sim_rows],
                          [p["simulate"]["peak_rss_mb"] for p in sim_rows])
    sim_st_lines = [f"| {p['n_station']} | {p['rows']:,} | {_cell(p['simulate'])} | "
                    f"{p['simulate']['peak_rss_mb']:.0f} |" for p in sim_st]
    e_sim_st = exponents([p["n_station"] for p in sim_st], [p["simulate"]["wall_s"] for p in sim_st])
    sthr = next((p for p in sim_rows if "threads1" in p), None)
    workers = []
    if thr:
        workers.append(f"| calibrate, {thr['rows']:,} rows | {thr['threads1']['wall_s']:.2f} | "
                       f"{thr['threads2']['wall_s']:.2f} | "
                       f"{thr['threads1']['wall_s'] / thr['threads2']['wall_s']:.2f} |")
    if sthr:
        workers.append(f"| simulate, {sthr['rows']:,} rows per band | "
                       f"{sthr['threads1']['wall_s']:.2f} | {sthr['threads2']['wall_s']:.2f} | "
                       f"{sthr['threads1']['wall_s'] / sthr['threads2']['wall_s']:.2f} |")
    return f"""## Scaling with rows, stations and workers (issue 7)

Machine: {machine_line()}; 1-minute load average {load[0]:.1f} at the start,
{load[1]:.1f} after the calibrate runs and {load[2]:.1f} at the end (shared machine:
wall times are upper bounds); whole benchmark {total / 60:.0f} min
(benchmarks/bench_scaling.py).  Whole processes; medians of n runs.

### hitops calibrate --method pwc against rows (8 stations, 4 correlations)

| rows per band | wall (s) | CPU (s) | peak RSS (MB) | I/O floor, issue (s) | x floor | I/O floor, same columns (s) | x floor | wall with --chunk-rows {CHUNK_ROWS:,} (s) | peak RSS with --chunk-rows (MB) |
|---|---|---|---|---|---|---|---|---|---|
{chr(10).join(lines)}

Growth exponents (wall ~ rows^k): k = {e_wall[0]:.2f} over all points, {e_wall[1]:.2f}
between the two largest; peak RSS ~ rows^{e_rss[0]:.2f} ({e_rss[1]:.2f} between the two
largest) with the default chunk of 2 000 000 rows, and ~ rows^{e_chunk[0]:.2f}
({e_chunk[1]:.2f}) with --chunk-rows {CHUNK_ROWS:,}.  The fixed start-up cost (about 0.7 s, see
the calibrate section) dominates below 10^6 rows, which is why the ratio to the I/O
floor falls as the data grow (at 10^7 rows calibrate is within {big_ratio:.1f}x the issue's
floor).

Memory ceiling: with --chunk-rows {CHUNK_ROWS:,} the peak grows by about
{per_row:.0f} bytes per row per band between the two largest points of this run; the
memory-only run (next section, `--memory-only`) measures the ceiling at more points.

### hitops calibrate against stations (1 h of 1 s, 4 correlations)

| stations | baselines | rows per band | wall (s) | peak RSS (MB) |
|---|---|---|---|---|
{chr(10).join(st_lines)}

wall ~ stations^{e_st[0]:.2f} over all points ({e_st[1]:.2f} between 16 and 30 stations;
rows grow as stations^2).

### hitops simulate against rows (30-station array, 435 baselines, both bands)

| rows per band | wall (s) | CPU (s) | peak RSS (MB) |
|---|---|---|---|
{chr(10).join(sim_lines)}

wall ~ rows^{e_sim[0]:.2f} over all points ({e_sim[1]:.2f} between the two largest);
peak RSS ~ rows^{e_sim_rss[0]:.2f} ({e_sim_rss[1]:.2f}): the simulator holds each band's
columns in memory.

### hitops simulate against stations (1 h of 1 s)

| stations | rows per band | wall (s) | peak RSS (MB) |
|---|---|---|---|
{chr(10).join(sim_st_lines)}

wall ~ stations^{e_sim_st[0]:.2f} ({e_sim_st[1]:.2f} between 16 and 30).

### Workers (threads on 2 cores; worker processes: see the distributed section)

| run | 1 worker (s) | 2 workers (s) | speed-up |
|---|---|---|---|
{chr(10).join(workers)}

calibrate's workers are dask's threaded scheduler (`DASK_NUM_WORKERS`), simulate's
`--threads`.  On a 2-core machine shared with other jobs the second worker can help
only the parts that run in parallel: the numba kernels release the GIL, and so does
casacore while it reads (a thread reading DATA and one running Python took the time of
the longer of the two, measured), but on a 10^6-row scene the kernels take ~0.2 s of a
~1.5 s process, so one or two workers differ by less than this machine's run-to-run
spread (repeated by hand: 1.4-3.2 s with one thread, 1.6-2.1 s with two).

![scaling]({fig.relative_to(PLOT_DIR.parent)})
"""


def plot(cal_rows, cal_st, sim_rows, sim_st, path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ax = axes[0]
    r = [p["rows"] for p in cal_rows]
    ax.loglog(r, [p["calibrate"]["wall_s"] for p in cal_rows], "o-", label="calibrate pwc")
    ax.loglog(r, [p["floors"]["issue"]["wall_s"] for p in cal_rows], "s--", label="I/O floor (issue)")
    ax.loglog(r, [p["floors"]["same_columns"]["wall_s"] for p in cal_rows], "^--",
              label="I/O floor (same columns)")
    rs = [p["rows"] for p in sim_rows]
    ax.loglog(rs, [p["simulate"]["wall_s"] for p in sim_rows], "D-", label="simulate (2 bands)")
    ax.set_xlabel("rows per band")
    ax.set_ylabel("wall time (s)")
    ax.legend(fontsize=7)
    ax = axes[1]
    ax.loglog(r, [p["calibrate"]["peak_rss_mb"] for p in cal_rows], "o-", label="calibrate, default chunk")
    ch = [p for p in cal_rows if "chunked" in p]
    ax.loglog([p["rows"] for p in ch], [p["chunked"]["peak_rss_mb"] for p in ch], "o--",
              label=f"calibrate, --chunk-rows {CHUNK_ROWS:,}")
    ax.loglog(rs, [p["simulate"]["peak_rss_mb"] for p in sim_rows], "D-", label="simulate")
    ax.set_xlabel("rows per band")
    ax.set_ylabel("peak RSS (MB)")
    ax.legend(fontsize=7)
    ax = axes[2]
    ax.loglog([p["n_ant"] for p in cal_st], [p["calibrate"]["wall_s"] for p in cal_st], "o-",
              label="calibrate (1 h)")
    ax.loglog([p["n_station"] for p in sim_st], [p["simulate"]["wall_s"] for p in sim_st], "D-",
              label="simulate (1 h)")
    ax.set_xlabel("stations")
    ax.set_ylabel("wall time (s)")
    ax.legend(fontsize=7)
    save_figure(fig, path)
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
