"""Wideband kernels (issue 26): throughput per visibility, and how much a band shrinks the n0 ambiguity.

Two measurements, written to the ``wideband`` section of docs/performance.md:

* throughput of :func:`hitops.kernels.wideband.row_delays` +
  :func:`~hitops.kernels.wideband.reference_phasors` (the reference band reduced to
  one phase per row) and :func:`~hitops.kernels.wideband.apply_channel_ratios`
  (one ratio per target channel) on ``--rows`` rows x 64 channels x 4
  correlations, beside a plain copy of the same array (the memory floor the
  kernels cannot beat), median of ``--repeat`` runs after a warm-up;
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
import time

import numpy as np

from hitops.kernels import wideband

from ._report import machine_line, replace_section

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=250_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    speed = throughput(args.rows, args.repeat)
    n0 = ambiguity()
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
    text = "\n".join(lines)
    print(text)
    replace_section("wideband", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
