"""Benchmark of ``hitops diagnose`` on a paper-scene-sized Measurement Set.

The MS (built with hitops.io.ms_create) has the paper's 8 stations (28
baselines), 12 h of 1 s samples (43 200 times, ~1.2 M rows), 4 correlations
and three columns: DATA (fBm troposphere, t_c = 10 s, plus noise),
CORRECTED_DATA (white phase noise, sigma 0.8 rad) and PWC_DATA (white phase
noise, sigma 0.3 rad).  The command is timed as a whole process (start-up,
imports, reading, 31 intervals = a 30-point grid plus --interval, tables; no
plots), then once more with plots.  Target (issue 4): <= 5 s wall on 2 cores
without plots.

Run: ``python -m benchmarks.bench_diagnose`` (writes the ``diagnose`` section of
docs/performance.md).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ._report import ROOT, machine_line, median, replace_section, run_process

sys.path.insert(0, str(ROOT / "tests"))

N_TIME = 43_200
STATIONS = ["AP", "SM", "PV", "GL", "PB", "KP", "KC", "KY"]
CORRS = ("RR", "RL", "LR", "LL")


def build(path: Path) -> Path:
    from test_diagnose_helpers import build_ms, fbm

    rng = np.random.default_rng(2023)
    n_bl = len(STATIONS) * (len(STATIONS) - 1) // 2
    shape = (n_bl, N_TIME, len(CORRS))
    raw = fbm(N_TIME, n_bl, 10.0, 1.0, rng)[:, :, None] + rng.normal(0, 0.3, shape)
    phases = {"DATA": raw,
              "CORRECTED_DATA": rng.normal(0, 0.8, shape),
              "PWC_DATA": rng.normal(0, 0.3, shape)}
    return build_ms(path, phases, STATIONS, corr_types=CORRS)


def main() -> None:
    workdir = Path(tempfile.mkdtemp(prefix="bench-diagnose-"))
    ms = workdir / "scene.ms"
    t0 = time.perf_counter()
    build(ms)
    build_s = time.perf_counter() - t0
    env = {"NUMBA_CACHE_DIR": str(ROOT / ".venv" / "numba-cache")}
    hitops = str(Path(sys.executable).with_name("hitops"))
    base = [hitops, "diagnose", str(ms), "--columns", "DATA,CORRECTED_DATA,PWC_DATA",
            "--correlations", ",".join(CORRS), "--intervals", "log:1:3600:30",
            "--interval", "60"]
    # first run warms the numba cache and the page cache; not reported
    run_process(base + ["--outdir", str(workdir / "warm")], env=env)
    runs = [run_process(base + ["--outdir", str(workdir / f"run{i}")], env=env)
            for i in range(5)]
    plots = run_process(base + ["--outdir", str(workdir / "plots"),
                                "--plots", "coherence,uv"], env=env)
    walls = [r["wall_s"] for r in runs]
    cpus = [r["cpu_s"] for r in runs]
    rss = max(r["peak_rss_mb"] for r in runs)
    import json
    mid = walls.index(median(walls))
    timing = json.loads((workdir / f"run{mid}" / "summary.json").read_text())["timing_s"]
    load = os.getloadavg()[0]
    ok = median(walls) <= 5.0
    text = f"""
## diagnose

`hitops diagnose` on a paper-sized MS: 8 stations (28 baselines), 43 200 one-second samples
(1 209 600 rows), 4 correlations, three columns (DATA, CORRECTED_DATA, PWC_DATA), C(T) on
31 intervals (log:1:3600:30 plus --interval 60). Whole process (start-up, imports, dask-ms read,
numba kernel on 2 threads, tables and JSON), no plots; median of 5 runs after one warm-up run.
Machine: {machine_line()}; benchmarks/bench_diagnose.py.

| quantity | value |
|---|---|
| wall, median of 5 (s) | {median(walls):.2f} (runs: {', '.join(f'{w:.2f}' for w in walls)}) |
| wall, best of 5 (s) | {min(walls):.2f} |
| CPU, median (s) | {median(cpus):.2f} |
| peak RSS (MB) | {rss:.0f} |
| inside the median run: read / coherence / total (s) | {timing['read']:.2f} / {timing['coherence']:.2f} / {timing['total']:.2f} |
| with `--plots coherence,uv` (wall, s) | {plots['wall_s']:.2f} |
| target <= 5 s wall without plots | {'met' if ok else 'NOT met'} |

C(T) of every baseline of this synthetic set (from the plotted run):
![C(T) per baseline](figures/diagnose-coherence-all.png)

(Building the synthetic MS took {build_s:.0f} s and is not included. The machine is shared;
the 1-minute load average at the end was {load:.1f}, so wall times include waiting for a core.)
"""
    print(text)
    replace_section("diagnose", text)
    import shutil
    figure = workdir / "plots" / "plots" / "coherence-all.png"
    if figure.exists():
        from ._report import PLOT_DIR
        PLOT_DIR.mkdir(parents=True, exist_ok=True)
        shutil.copy(figure, PLOT_DIR / "diagnose-coherence-all.png")
    shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
