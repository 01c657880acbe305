"""Wideband kernels (issue 26): throughput per visibility, and how much a band shrinks the n0 ambiguity.

Two measurements, written to the ``wideband`` section of docs/performance.md:

* throughput of :func:`hitops.kernels.wideband.row_delays` +
  :func:`~hitops.kernels.wideband.reference_phasors` (the reference band reduced to
  one phase per row) and :func:`~hitops.kernels.wideband.apply_channel_ratios`
  (one ratio per target channel) on ``--rows`` rows x 64 channels x 4
  correlations, beside a plain copy of the same array (the memory floor the
  kernels cannot beat), median of ``--repeat`` runs after a warm-up;
* ``hitops calibrate`` as a whole process on a simulated pair of ``--cal-rows`` rows
  x 64 channels x 4 correlations per band (5 stations, the demo scene's hour cut
  into short integrations, no noise), default options and ``--no-verdict``, beside
  the same-columns I/O floor (benchmarks/_floors.py: both bands' metadata, DATA
  and FLAG read, one column written), run by run (interleaved), with the peak
  resident memory; ``--cal-rows 0`` skips it;
* the n0 step's ambiguity: PWC counted from n'(t0) = 0 while the true count
  started at n0 (uniform in [-100, 100]); the reference column is good to
  sigma degrees (one error common to all channels); the candidate k in
  [-200, 200] with the best :func:`~hitops.kernels.wideband.channel_offset_scores`
  is taken.  One channel at 230 GHz against two 2-GHz windows of 16 x 125 MHz
  at 227.1 and 229.1 GHz, 200 trials each.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from hitops.kernels import wideband

from ._floors import measure_floors
from ._report import machine_line, replace_section, run_process

REF_FREQ = 86.0e9
REF_CHANS = REF_FREQ + (np.arange(64) - 31.5) * 31.25e6
TGT_CHANS = 228.1e9 + (np.arange(64) - 31.5) * 62.5e6
BAND = np.concatenate([227.1e9 + (np.arange(16) - 7.5) * 125e6,
                       229.1e9 + (np.arange(16) - 7.5) * 125e6])


def timed(fn, repeat):
    fn()                                        # numba compile / page-in
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def throughput(n_row: int, repeat: int) -> list:
    rng = np.random.default_rng(0)
    shape = (n_row, 64, 4)
    vis = np.exp(1j * rng.uniform(-np.pi, np.pi, shape)).astype(np.complex64)
    ok = np.ones(shape, bool)
    phase = rng.uniform(-50, 50, (n_row, 4))
    valid = np.ones((n_row, 4), bool)
    ratios = TGT_CHANS / REF_FREQ
    n_vis = vis.size

    def reduce():
        wideband.reference_phasors(vis, ok, REF_CHANS, REF_FREQ,
                                   wideband.row_delays(vis, ok, REF_CHANS))

    rows = [("copy of the visibilities (memory floor)", timed(lambda: vis.copy(), repeat)),
            ("reference: delay fit + phase at nu_ref", timed(reduce, repeat)),
            ("target: one ratio per channel", timed(
                lambda: wideband.apply_channel_ratios(vis, ok, phase, valid, ratios), repeat))]
    return [(name, t, n_vis / t) for name, t in rows]


def ambiguity(trials: int = 200) -> list:
    rng = np.random.default_rng(1)
    ks = np.arange(-200, 201, dtype=np.int64)
    out = []
    for sigma in (2, 5, 10, 30):
        for name, freqs in (("one channel at 230 GHz", np.array([230e9])),
                            ("2 x 16 x 125 MHz at 227.1/229.1 GHz", BAND)):
            ratios = freqs / REF_FREQ
            wrong = 0
            for _ in range(trials):
                n0 = int(rng.integers(-100, 101))
                z = np.exp(1j * (2 * np.pi * ((ratios * n0) % 1)
                                 + np.deg2rad(sigma) * rng.standard_normal()))
                wrong += ks[np.argmax(wideband.channel_offset_scores(z, ratios, ks))] != n0
            out.append((sigma, name, wrong, trials))
    return out


SCENE = """name: bench-wideband
source: {{name: M87, ra: "12h30m49.42s", dec: "+12d23m28.04s", flux: {{"86": 1.1, "230": 1.0}}}}
observation:
  start: "2023-04-10T02:00:00"
  duration: 3600
  integration: {integration}
  correlations: [RR, RL, LR, LL]
bands:
  - {{name: "86", freq_ghz: 86, bandwidth_ghz: 2, n_chan: 64}}
  - {{name: "230", freq_ghz: 230, bandwidth_ghz: 2, n_chan: 64}}
corruptions: {{troposphere: true, noise: false, seed: 7, coherence_freq_ghz: 230}}
stations: [AP, PV, GL, PB, KP]
"""


def calibrate_runs(workdir: Path, n_rows: int, repeats: int) -> dict:
    """Whole-process calibrate (default, --no-verdict) and the same-columns floor, interleaved."""
    workdir.mkdir(parents=True, exist_ok=True)
    scene = workdir / "scene.yml"
    # 10 baselines, all up for the hour: n_rows / 10 integrations
    scene.write_text(SCENE.format(integration=3600 * 10 / n_rows))
    ref, tgt = workdir / "sim-86.ms", workdir / "sim-230.ms"
    if not (tgt / "table.dat").exists():
        run_process([sys.executable, "-m", "hitops.cli", "simulate", str(scene), "--outdir",
                     str(workdir), "--overwrite"])
    base = [sys.executable, "-m", "hitops.cli", "calibrate", str(ref), str(tgt), "--method",
            "pwc", "--overwrite", "--report", str(workdir / "report.json")]
    commands = {"default": base, "no_verdict": base + ["--no-verdict"]}
    run_process(commands["no_verdict"])           # warm-up: numba cache, page cache
    runs = {name: [] for name in (*commands, "floor")}
    for _ in range(repeats):
        for name, cmd in commands.items():
            runs[name].append(run_process(cmd))
        runs["floor"].append(measure_floors(workdir, ref, tgt, repeats=1,
                                            names=["same_columns"])["same_columns"])
    return {name: {"wall_s": [r["wall_s"] for r in rs],
                   "peak_rss_mb": max(r["peak_rss_mb"] for r in rs)} for name, rs in runs.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=250_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cal-rows", type=int, default=1_000_000)
    parser.add_argument("--workdir", type=Path, default=Path("bench-out/wideband"))
    args = parser.parse_args(argv)
    speed = throughput(args.rows, args.repeat)
    n0 = ambiguity()
    cal = calibrate_runs(args.workdir, args.cal_rows, args.repeat) if args.cal_rows else None
    load = os.getloadavg()[0]
    lines = ["## Wideband kernels", "",
             f"Machine: {machine_line()}, load average {load:.1f}; {args.rows} rows x 64 channels x 4 correlations "
             f"({args.rows * 256 / 1e6:.0f} M visibilities), median of {args.repeat}, "
             "one thread (`python -m benchmarks.bench_wideband`).", "",
             "| step | time (s) | visibilities per second |", "|---|---|---|"]
    lines += [f"| {name} | {t:.3f} | {rate / 1e6:.0f} M |" for name, t, rate in speed]
    lines += ["", "n0 from a reference good to sigma (common to all channels), true n0 in "
              "[-100, 100], candidates [-200, 200]:", "",
              "| sigma (deg) | target | wrong n0 |", "|---|---|---|"]
    lines += [f"| {sigma} | {name} | {wrong}/{trials} |" for sigma, name, wrong, trials in n0]
    if cal:
        floor = statistics.median(cal["floor"]["wall_s"])
        n_vis = 2 * args.cal_rows * 64 * 4
        lines += ["", f"`hitops calibrate --method pwc` on {args.cal_rows} rows x 64 channels x 4 "
                  "correlations per band (both bands, a 2-GHz window each; troposphere, no "
                  "noise), whole process, interleaved runs:", "",
                  "| run | wall (s), each run | median / floor | visibilities per second | peak memory (MB) |",
                  "|---|---|---|---|---|"]
        for name, label in (("floor", "same-columns I/O floor"), ("default", "default options"),
                             ("no_verdict", "`--no-verdict`")):
            walls = cal[name]["wall_s"]
            med = statistics.median(walls)
            lines.append(f"| {label} | {', '.join(f'{w:.1f}' for w in walls)} | {med / floor:.2f} "
                         f"| {n_vis / med / 1e6:.1f} M | {cal[name]['peak_rss_mb']:.0f} |")
    text = "\n".join(lines)
    print(text)
    replace_section("wideband", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
