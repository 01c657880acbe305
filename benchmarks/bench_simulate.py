"""Benchmarks of ``hitops simulate`` (section ``simulate`` of docs/performance.md).

1. Troposphere generators: structure-function error against generation time
   for exact circulant embedding, dense Cholesky, plain FFT power-law
   synthesis and a random walk (figure docs/figures/simulate_troposphere.png).
2. Speed: the paper's scene, both bands with troposphere and noise, as one
   ``hitops simulate`` process, beside casatools.simulator laying out one
   band of the same scene (no corruption, no noise) in the same run; wall
   time, CPU time and peak RSS of each process.  Also the same scene with
   every (baseline, time) row kept (elevation limit -90 deg), the row count
   casatools.simulator writes.

Run: ``python benchmarks/bench_simulate.py [--quick]`` (--quick skips CASA).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import PLOT_DIR, ROOT, machine_line, replace_section, run_process, save_figure  # noqa: E402

from hitops.simulate import troposphere as tp  # noqa: E402
from hitops.simulate.scene import load_scene_mapping  # noqa: E402

PYTHON = sys.executable


def troposphere_tradeoff(n_series: int = 64, repeats: int = 3, n_ensemble: int = 1024):
    """Rows of (method, n, seconds per series, max |D/D_theory - 1| over lags 1..n/4)."""
    sizes = {"circulant": [256, 1024, 4096, 16384, 43200],
             "cholesky": [256, 1024, 2048, 4096],
             "fft_powerlaw": [256, 1024, 4096, 16384, 43200],
             "random_walk": [256, 1024, 4096, 16384, 43200]}
    rows = []
    for method, ns in sizes.items():
        generator = tp.GENERATORS[method]
        for n in ns:
            rng = np.random.default_rng(n)
            best = np.inf
            series = None
            for _ in range(repeats):
                t0 = time.perf_counter()
                series = generator(n, n_series, tp.HURST_KOLMOGOROV, rng)
                best = min(best, time.perf_counter() - t0)
            # a larger ensemble for the error itself (its statistical floor is ~2-3%)
            big = np.concatenate([series] + [generator(n, n_series, tp.HURST_KOLMOGOROV, rng)
                                             for _ in range(max(1, n_ensemble // n_series) - 1)])
            lags = np.unique(np.geomspace(1, n // 4, 8).astype(int))
            measured = tp.structure_function(big, lags)
            error = np.max(np.abs(measured / lags ** (5.0 / 3.0) - 1.0))
            rows.append((method, n, best / n_series, error))
            print(f"{method:13s} n={n:6d} {1e3 * best / n_series:9.3f} ms/series  "
                  f"max SF error {100 * error:6.1f}%", flush=True)
    return rows


def plot_tradeoff(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for method, marker in (("circulant", "o"), ("cholesky", "s"), ("fft_powerlaw", "^"),
                           ("random_walk", "v")):
        sel = [r for r in rows if r[0] == method]
        ax.plot([r[2] for r in sel], [100 * r[3] for r in sel], marker=marker, label=method)
        for r in sel:
            ax.annotate(str(r[1]), (r[2], 100 * r[3]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axhline(5, color="grey", ls=":", lw=1)
    ax.set_xlabel("generation time per station series (s)")
    ax.set_ylabel("max |D(dt)/(dt/t_c)^{5/3} - 1| over dt = 1 .. n/4 (%)")
    ax.set_title("Kolmogorov phase generators (labels: n samples)")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def all_rows_scene(work: Path) -> Path:
    """The paper's scene with every (baseline, time) row: elevation limit -90 deg."""
    scene, _ = load_scene_mapping("paper")
    scene["stations"] = [{"code": code, "elevation_limit": -90} for code in scene["stations"]]
    path = work / "paper-all-rows.yml"
    path.write_text(yaml.safe_dump(scene))
    return path


def n_rows(ms: Path) -> int:
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        return t.nrows()


def speed(work: Path, with_casa: bool):
    env = {"NUMBA_CACHE_DIR": str(ROOT / ".venv" / "numba-cache")}
    results = []
    # warm the numba cache once so the timed runs measure the steady state
    run_process([PYTHON, "-m", "hitops.cli", "simulate", "demo", "--outdir", str(work / "warm"),
                 "--overwrite"], env=env)
    for label, scene in (("paper scene (rows while both stations are up)", "paper"),
                         ("paper scene, every row (elevation limit -90 deg)",
                          str(all_rows_scene(work)))):
        out = work / ("hitops-" + ("paper" if scene == "paper" else "all"))
        res = run_process([PYTHON, "-m", "hitops.cli", "simulate", scene, "--outdir", str(out),
                           "--overwrite", "--save-truth"], env=env)
        res["rows"] = n_rows(out / "sim-86.ms")
        res["label"] = f"hitops simulate, both bands, troposphere + noise: {label}"
        results.append(res)
        print(res["label"], f"{res['wall_s']:.1f} s, {res['peak_rss_mb']:.0f} MB, "
              f"{res['rows']} rows/band", flush=True)
    if with_casa:
        casa_ms = work / "casa-86.ms"
        res = run_process([PYTHON, str(ROOT / "benchmarks" / "casa_layout.py"), "paper",
                           str(casa_ms), "--band", "86"], env=env)
        res["rows"] = n_rows(casa_ms)
        res["label"] = "casatools.simulator layout, ONE band, no corruption, no noise"
        results.append(res)
        print(res["label"], f"{res['wall_s']:.1f} s, {res['peak_rss_mb']:.0f} MB, "
              f"{res['rows']} rows", flush=True)
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="skip the CASA simulator run")
    args = parser.parse_args(argv)

    # speed first: a forked child's peak RSS counts the parent's pages until exec,
    # so the processes must be timed while this one is still small
    with tempfile.TemporaryDirectory(prefix="bench-simulate-") as tmp:
        results = speed(Path(tmp), with_casa=not args.quick)

    rows = troposphere_tradeoff()
    figure = PLOT_DIR / "simulate_troposphere.png"
    plot_tradeoff(rows, figure)

    lines = ["## hitops simulate", "",
             f"Machine: {machine_line()}; run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} "
             "by `python benchmarks/bench_simulate.py` (machine shared with other jobs, so "
             "wall times are upper bounds).", "",
             "### Speed: the paper's scene (8 stations, 12 h, 1 s, 86 + 230 GHz)", "",
             "| run | rows per band | wall (s) | CPU (s) | peak RSS (MB) |",
             "|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['label']} | {r['rows']:,} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                     f"{r['peak_rss_mb']:.0f} |")
    casa = [r for r in results if r["label"].startswith("casatools")]
    if casa:
        full = results[1]
        lines += ["", f"Ratio, casatools.simulator (one band, layout only) to hitops simulate "
                      f"(both bands, troposphere, noise, truth) at the same row count "
                      f"({full['rows']:,} rows per band): "
                      f"**{casa[0]['wall_s'] / full['wall_s']:.1f}x** in wall time, "
                      f"{casa[0]['peak_rss_mb'] / full['peak_rss_mb']:.1f}x in peak RSS; "
                      f"for the paper's real scene (rows only while both stations are up): "
                      f"**{casa[0]['wall_s'] / results[0]['wall_s']:.1f}x**.  Target was "
                      "<= 20 s for both bands."]
    lines += ["", "Where the time goes (paper scene, hitops' own log, quiet machine / load 4.5): "
              "time grid, casacore UVW matrices sampled every 60 s and fitted, elevations, "
              "rows and the troposphere (8 x 43,200 samples) 0.4 / 1.3 s; visibilities and "
              "noise 0.1 s per band (plus ~0.5 s once to load the cached numba kernel); "
              "Measurement Set writing 0.5 s per band, since the main table uses "
              "TiledColumnStMan for DATA/FLAG/SIGMA/WEIGHT/UVW, one StandardStMan per "
              "per-row scalar and an IncrementalStMan for the constant columns (a single "
              "StandardStMan for everything, the previous layout, took ~3.5 s per 1.2 M "
              "rows, most of it in addrows); the rest is Python, numba and casacore "
              "start-up and the truth file.",
              "", "### Troposphere generators: structure-function error against run time", "",
              "![structure-function error vs time](figures/simulate_troposphere.png)", "",
              "Error = max over lags 1 .. n/4 samples of |D_measured/D_theory - 1| from a "
              "1024-series ensemble (its statistical floor, 2-3% at the longest lags, is what "
              "the exact methods show); time = best of 3, per series, 64 series per call "
              "(the Cholesky factor is shared by them).", "",
              "| method | n | ms per series | max SF error |", "|---|---|---|---|"]
    for method, n, secs, err in rows:
        lines.append(f"| {method} | {n} | {1e3 * secs:.3f} | {100 * err:.1f}% |")
    lines += ["", "Circulant embedding is exact (its error is the ensemble's statistical "
              "floor) at O(n log n); dense Cholesky is exact too but O(n^3) in time and "
              "O(n^2) in memory (n = 43,200 would need 15 GB); plain FFT synthesis of the "
              "power law loses the power below 1/T and underestimates long lags; a random "
              "walk has D ~ dt, the wrong exponent."]
    replace_section("simulate", "\n".join(lines))
    print("wrote section 'simulate' of docs/performance.md and", figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
