"""Benchmark of ``hitops calibrate --method pwc`` on a paper-size pair (issue 2).

Scene (hitops.calibrate.synthetic.make_pair): the paper's 8 stations (28
baselines), 12 h of 1 s integrations (43 200 times, 1 209 600 rows per band),
4 correlations, one channel, random-walk troposphere with thermal noise.
Each figure is a whole process (start-up, imports, reading, FPT, writing)
measured by benchmarks/_report.run_process:

* floors (benchmarks/_floors.py): the issue's I/O floor (a python-casacore
  script that reads the two DATA columns and writes one output column), the
  same with every column calibrate reads, and an imports-only process;
* ``hitops calibrate --method pwc`` with a cold numba cache (fresh
  NUMBA_CACHE_DIR: every kernel compiles) and with a warm cache (median of 3).

Targets on this 2-core machine: <= 2 s wall warm, <= 1 GB peak RSS, <= 3x the
I/O floor.  The machine is shared, so the 1-minute load average is recorded
beside the figures.

Run: ``python -m benchmarks.bench_calibrate [--workdir DIR]`` (writes the
``calibrate`` section of docs/performance.md).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ._floors import LABELS as FLOOR_LABELS, measure_floors
from ._report import PLOT_DIR, machine_line, median, replace_section, run_process, save_figure

N_TIME = 43_200
N_ANT = 8
CORRS = ("RR", "RL", "LR", "LL")

def build(workdir: Path):
    from hitops.calibrate.synthetic import make_pair

    if (workdir / "target.ms" / "table.dat").exists() and (workdir / "ref.ms" / "table.dat").exists():
        return workdir / "ref.ms", workdir / "target.ms"
    t0 = time.perf_counter()
    truth = make_pair(workdir, n_ant=N_ANT, n_time=N_TIME, corr_types=CORRS, step_rad=0.05,
                      drift_rad=0.01, sigma_ref=0.05, sigma_target=0.1, seed=2023)
    print(f"built the pair in {time.perf_counter() - t0:.1f} s", flush=True)
    return truth.ref_ms, truth.target_ms


def figure(path: Path) -> Path:
    """CFPT and PWC residuals of one synthetic baseline with the reference wraps marked.

    The analogue of the paper's Fig. (cfpt_vs_pwc_phase_w_wrap_positions), made by
    running the tool itself on a small pair with a known source phase.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from casacore import tables as pt

    from hitops.calibrate import calibrate
    from hitops.calibrate.synthetic import make_pair, wrap
    from hitops.kernels.wraps import count_wraps

    workdir = Path(tempfile.mkdtemp(prefix="fig-calibrate-"))
    truth = make_pair(workdir, n_ant=3, n_time=1800, step_rad=0.04, drift_rad=0.03,
                      sigma_ref=0.03, sigma_target=0.08, phase_offset_rad=1.0, seed=5)
    calibrate(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    with pt.table(str(truth.target_ms), ack=False) as t:
        cfpt = np.angle(t.getcol("CFPT_DATA")[:, 0, 0])
        pwc = np.angle(t.getcol("PWC_DATA")[:, 0, 0])
    with pt.table(str(truth.ref_ms), ack=False) as t:
        ref = np.angle(t.getcol("DATA")[:, 0, 0]).astype(np.float64)
    sel = (truth.ant1 == 0) & (truth.ant2 == 1)
    order = np.argsort(truth.time[sel])
    minutes = (truth.time[sel][order] - truth.time.min()) / 60.0
    source = truth.source_phase[sel][order, 0]
    n = count_wraps(ref[sel][order], np.ones(order.size, bool))
    fig, ax = plt.subplots(figsize=(8, 3.4))
    for t_wrap in minutes[1:][np.diff(n) != 0]:
        ax.axvline(t_wrap, color="0.8", lw=0.6, ls="--", zorder=0)
    ax.plot(minutes, np.degrees(wrap(cfpt[sel][order] - source)), ".", ms=1.5, label="CFPT")
    ax.plot(minutes, np.degrees(wrap(pwc[sel][order] - source)), ".", ms=1.5, label="PWC")
    ax.set_xlabel("time (min)")
    ax.set_ylabel("residual phase at 230 GHz (deg)")
    ax.set_ylim(-185, 185)
    ax.set_title("R = 230/86: CFPT jumps by -117.2 deg at every 86 GHz wrap (dashed); PWC does not",
                 fontsize=9)
    ax.legend(markerscale=6, loc="lower left", fontsize=8)
    save_figure(fig, path)
    shutil.rmtree(workdir, ignore_errors=True)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None, help="where to build (and reuse) the pair")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv if argv is not None else [])
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-calibrate-"))
    workdir.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = build(workdir)
    hitops = str(Path(sys.executable).with_name("hitops"))
    command = [hitops, "calibrate", str(ref_ms), str(target_ms), "--method", "pwc",
               "--overwrite", "--report", str(workdir / "report.json")]

    floors = measure_floors(workdir, ref_ms, target_ms, repeats=args.repeats)

    cold_cache = Path(tempfile.mkdtemp(prefix="numba-cold-"))
    load_before = os.getloadavg()[0]
    cold = run_process(command, env={"NUMBA_CACHE_DIR": str(cold_cache)})
    warm_runs = [run_process(command, env={"NUMBA_CACHE_DIR": str(cold_cache)})
                 for _ in range(args.repeats)]
    chunked_command = command[:-1] + [str(workdir / "report-chunked.json"), "--chunk-rows", "200000"]
    chunked = run_process(chunked_command, env={"NUMBA_CACHE_DIR": str(cold_cache)})
    load_after = os.getloadavg()[0]
    shutil.rmtree(cold_cache, ignore_errors=True)

    import json
    last_report = json.loads((workdir / "report.json").read_text())
    stages = last_report.get("timings_s", {})
    in_tool = last_report.get("time_s", float("nan"))
    n_chunks = json.loads((workdir / "report-chunked.json").read_text()).get("chunks")
    floor = floors["issue"]["wall_s"]
    fair = floors["same_columns"]["wall_s"]
    imports = floors["imports"]["wall_s"]
    warm = median([r["wall_s"] for r in warm_runs])
    warm_cpu = median([r["cpu_s"] for r in warm_runs])
    warm_rss = max(r["peak_rss_mb"] for r in warm_runs)
    rows = [(FLOOR_LABELS[k], v["wall_s"], v["cpu_s"], v["peak_rss_mb"])
            for k, v in floors.items()]
    rows += [
        ("hitops calibrate --method pwc, cold numba cache", cold["wall_s"], cold["cpu_s"],
         cold["peak_rss_mb"]),
        (f"hitops calibrate --method pwc, warm cache (median of {args.repeats}; runs "
         + ", ".join(f"{r['wall_s']:.2f}" for r in warm_runs) + ")", warm, warm_cpu, warm_rss),
        (f"same, --chunk-rows 200000 ({n_chunks} time chunks, wrap counts carried)", chunked["wall_s"],
         chunked["cpu_s"], chunked["peak_rss_mb"]),
    ]
    table = "\n".join(f"| {name} | {w:.2f} | {c:.2f} | {m:.0f} |" for name, w, c, m in rows)
    stage_line = ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
    best = min(r["wall_s"] for r in warm_runs)
    work = sum(stages.get(k, 0.0) for k in ("metadata", "match", "read", "transfer", "write"))
    stack = imports + 0.2
    stack_verdict = ("more than the whole budget" if stack > 3 * floor else
                     f"leaving {3 * floor - stack:.2f} s for the work")
    verdict = (f"warm wall {warm:.2f} s, best of {len(warm_runs)} {best:.2f} s "
               f"(target <= 2 s: {'met' if warm <= 2 else 'NOT met'} by the median), "
               f"{warm / floor:.1f}x the issue's I/O floor (target <= 3x: "
               f"{'met' if warm <= 3 * floor else 'NOT met'}; {warm / fair:.1f}x the floor "
               f"reading the same columns), peak RSS {warm_rss:.0f} MB "
               f"(target <= 1024 MB: {'met' if warm_rss <= 1024 else 'NOT met'})")
    markdown = f"""## hitops calibrate (issue 2)

Machine: {machine_line()}; 1-minute load average {load_before:.1f} before and
{load_after:.1f} after the runs (the machine is shared; wall times grow with load, CPU
times much less).  Scene: {N_ANT} stations (28 baselines), {N_TIME} times of 1 s,
{len(CORRS)} correlations, one channel: {28 * N_TIME} rows per band
(hitops.calibrate.synthetic.make_pair).  Whole processes (benchmarks/_report.run_process).

| run | wall (s) | CPU (s) | peak RSS (MB) |
|---|---|---|---|
{table}

Verdict: {verdict}.

Against the paper: its PWC calibration of the 230 GHz set of the same size (8
stations, 12 h of 1 s, ~1.2 M rows, 4 correlations) took under 20 s on two logical
cores with 6.5 GB; here the whole `hitops calibrate --method pwc` process takes
{warm:.2f} s warm ({20 / warm:.0f}x less than 20 s) and {cold["wall_s"]:.2f} s with a cold numba
cache, with a peak RSS of {warm_rss / 1024:.2f} GB ({6.5 * 1024 / warm_rss:.0f}x less than 6.5 GB).

Stages of the last warm run (seconds, from the report's `timings_s`): {stage_line}.
They add up to {in_tool:.2f} s inside `calibrate()`; the rest of the process wall time
(about {warm - in_tool:.2f} s) is Python start-up and the imports done before `calibrate()`
is entered (click and the schemas, numpy, and whatever calibrate imports at module
level).  `checks` is input validation plus the imports it triggers (numba through
the kernels' tracker registry, python-casacore); `open` includes importing dask-ms (about 0.3 s
idle, most of it dask.array, which itself imports scipy.sparse and scipy.fftpack, and
fsspec) and building the two lazy datasets; `metadata` reads TIME/ANTENNA1/ANTENNA2/
SCAN_NUMBER/INTERVAL/FLAG_ROW of both bands, `match` matches the bands, `read` reads DATA
and FLAG and grids them, `transfer` counts wraps and runs the PWC kernels (including
numba's first kernel load from its cache, about 0.2 s of LLVM start-up per process),
`write` writes the output column through dask-ms.

What was cut (hitops/io/read.py, perf engineer): dask-ms's row-ordering query
`SELECT ROWID() AS __tablerow__ FROM $1`, which evaluates an expression on every row
(0.2 s per 1.2 M-row table, holding the GIL) only to return 0..n-1 when no
`index_cols`/`taql_where` is given, is no longer run: the datasets are built by dask-ms's
own dataset factory with the storage order given directly (reads still go through its
table proxy and getcol wrappers; tests/test_io_read.py checks the result equals
`xds_from_ms(..., index_cols=[], group_cols=[])`); the output arrays are handed to
`xds_to_table` without `dask.array.from_array`'s copy (0.1 s and 40 MB).  Together
about 0.5 s and 100 MB of peak RSS less than before (2.45-2.7 s, 810 MB, measured
at load ~2; the same code measured 1.6-2.5 s, median 2.0-2.2 s, in quieter moments).
Also (hitops/io/match.py) the band matching keeps int32 indices built through small
antenna-pair lookup tables (20 instead of 140 bytes per row at its peak), and
(hitops/io/read.py) a time chunk's rows are read as a dask-ms dataset of exactly those
rows (before, slicing the whole-table dataset made dask-ms read every 2 M-row block a
chunk touched: `--chunk-rows` was 4x slower at 10^7 rows).

Which targets are within reach: the imports-only process above ({imports:.2f} s) is the
fixed cost of the required stack (numba kernels, I/O through dask-ms) before any data is
touched; with numba's first kernel load (~0.2 s) that is {stack:.2f} s of the {3 * floor:.2f} s
that 3x the issue's I/O floor allows, {stack_verdict}, while the work proper (metadata,
match, read, FPT, write: {work:.2f} s in the last warm run) is itself {work / floor:.1f}x the
floor.  The 3x ratio is out of reach for this stack on a scene this small (at 10^7 rows,
where start-up no longer dominates, calibrate is within about 2x: see the scaling
section).  The issue's floor is also not the same work: calibrate reads 8 columns of
each band (metadata and flags too), so the same-columns floor is the fair comparison.
Both floors read from the page cache (the sets were just written), so they measure
memory copies, not disks, and vary with the machine's load as much as calibrate does.
Memory: one chunk holds the whole scene here; `--chunk-rows` bounds the visibility data
(row above), not the per-row metadata of the whole track (scaling section).

Run: `python -m benchmarks.bench_calibrate [--workdir DIR]`.
"""
    print(markdown)
    replace_section("calibrate", markdown)
    print("figure:", figure(PLOT_DIR / "calibrate_cfpt_vs_pwc.png"))
    if not args.workdir:   # a pair built in a temporary directory is not kept
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
