"""Benchmark of ``hitops calibrate --method pwc`` on a paper-size pair (issue 2).

Scene (hitops.calibrate.synthetic.make_pair): the paper's 8 stations (28
baselines), 12 h of 1 s integrations (43 200 times, 1 209 600 rows per band),
4 correlations, one channel, random-walk troposphere with thermal noise.
Each figure is a whole process (start-up, imports, reading, FPT, writing)
measured by benchmarks/_report.run_process:

* I/O floor: a python-casacore script that reads the two DATA columns and
  writes one output column;
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

from ._report import PLOT_DIR, machine_line, median, replace_section, run_process

N_TIME = 43_200
N_ANT = 8
CORRS = ("RR", "RL", "LR", "LL")

IO_FLOOR = """
import sys
import numpy as np
from casacore import tables as pt
ref, target = sys.argv[1], sys.argv[2]
with pt.table(ref, ack=False) as t:
    ref_data = t.getcol("DATA")
with pt.table(target, readonly=False, ack=False) as t:
    data = t.getcol("DATA")
    if "FLOOR_DATA" not in t.colnames():
        desc = t.getcoldesc("DATA")
        desc["name"] = "FLOOR_DATA"
        t.addcols(pt.makecoldesc("FLOOR_DATA", desc))
    t.putcol("FLOOR_DATA", data)
"""


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
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    shutil.rmtree(workdir, ignore_errors=True)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None, help="where to build (and reuse) the pair")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv if argv is not None else [])
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-calibrate-"))
    workdir.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = build(workdir)
    hitops = str(Path(sys.executable).with_name("hitops"))
    command = [hitops, "calibrate", str(ref_ms), str(target_ms), "--method", "pwc",
               "--overwrite", "--report", str(workdir / "report.json")]

    floor_script = workdir / "io_floor.py"
    floor_script.write_text(IO_FLOOR)
    floor_runs = [run_process([sys.executable, str(floor_script), str(ref_ms), str(target_ms)])
                  for _ in range(args.repeats)]

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
    floor = median([r["wall_s"] for r in floor_runs])
    warm = median([r["wall_s"] for r in warm_runs])
    warm_cpu = median([r["cpu_s"] for r in warm_runs])
    warm_rss = max(r["peak_rss_mb"] for r in warm_runs)
    rows = [
        ("I/O floor (python-casacore: read 2 x DATA, write 1 column)", floor,
         median([r["cpu_s"] for r in floor_runs]), max(r["peak_rss_mb"] for r in floor_runs)),
        ("hitops calibrate --method pwc, cold numba cache", cold["wall_s"], cold["cpu_s"],
         cold["peak_rss_mb"]),
        (f"hitops calibrate --method pwc, warm cache (median of {args.repeats})", warm, warm_cpu,
         warm_rss),
        (f"same, --chunk-rows 200000 ({n_chunks} time chunks, wrap counts carried)", chunked["wall_s"],
         chunked["cpu_s"], chunked["peak_rss_mb"]),
    ]
    table = "\n".join(f"| {name} | {w:.2f} | {c:.2f} | {m:.0f} |" for name, w, c, m in rows)
    stage_line = ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
    verdict = (f"warm wall {warm:.2f} s (target <= 2 s: {'met' if warm <= 2 else 'NOT met'}), "
               f"{warm / floor:.1f}x the I/O floor (target <= 3x: "
               f"{'met' if warm <= 3 * floor else 'NOT met'}), peak RSS {warm_rss:.0f} MB "
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

Stages of the last warm run (seconds, from the report's `timings_s`): {stage_line}.
They add up to {in_tool:.2f} s inside `calibrate()`; the rest of the process wall time
(about {warm - in_tool:.2f} s) is Python start-up and imports (numpy, numba, dask,
dask-ms, python-casacore, click) not done lazily.  `checks` is input validation (and
the casacore import), `open` is importing dask-ms (about 0.35 s, most of it dask.array)
and dask-ms building the two datasets (its row-ordering TaQL query,
`SELECT ROWID() ... FROM $1`, over every row of each table: about 0.2 s per
1.2 M-row table when the machine is idle), `metadata` reading TIME/ANTENNA1/ANTENNA2/SCAN_NUMBER/INTERVAL/
FLAG_ROW of both bands, `match` the band matching, `read` the DATA and FLAG columns,
`transfer` gridding, wrap counting and the PWC kernels (it includes numba's first
kernel load from the cache, about 0.2 s of LLVM start-up per process), `write` the
output column through dask-ms.

Why the wall-time targets are missed: start-up and imports, numba's first load and
dask-ms's ordering query are fixed costs of the required stack (numba kernels, I/O
through dask-ms) that together take about 1.5 s before any data is touched; the
tiled I/O floor of this scene is far below that.  The work proper (metadata, match,
read, FPT, write) is well under a second.  Memory: one chunk holds the whole scene;
`--chunk-rows` bounds it (row above) at the price of per-chunk dask-ms overhead.

Run: `python -m benchmarks.bench_calibrate [--workdir DIR]`.
"""
    print(markdown)
    replace_section("calibrate", markdown)
    print("figure:", figure(PLOT_DIR / "calibrate_cfpt_vs_pwc.png"))
    if not args.workdir:   # a pair built in a temporary directory is not kept
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
