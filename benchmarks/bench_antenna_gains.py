"""Antenna gains (the caltable, and --tracker antenna's column) against baseline PWC, with noise.

For issue 13: with thermal noise the antenna-based solution (each station's reference
phase solved from all its baselines) and the baseline-based one (each baseline's own
reference phase) differ.  Both are compared with the truth on synthetic pairs with a
point source at the reference band (hitops.testing.make_pair,
ref_offset_scale=0), per-sample reference SNR rho = 1.1 / sigma: the residual phase of
the output around its per-(baseline, scan) mean, which is what transferred reference
noise adds (the n0 constants are removed with the mean).  Prints a markdown table.

    .venv/bin/python -m benchmarks.bench_antenna_gains
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np


def residual_rms_deg(truth, out):
    """RMS (deg) of the output phase minus the source, around each (baseline, scan) mean."""
    y = np.exp(1j * (np.angle(out[:, 0, :]) - truth.source_phase))
    key = (truth.ant1 * 100 + truth.ant2) * 1000 + truth.scan
    res = []
    for k in np.unique(key):
        sel = key == k
        for c in range(y.shape[1]):
            z = y[sel, c]
            res.append(np.angle(z * np.conj(np.mean(z))))
    return float(np.degrees(np.sqrt(np.mean(np.concatenate(res) ** 2))))


def main():
    from casacore import tables as pt

    from hitops.calibrate import calibrate_flat
    from hitops.testing import PairSpec, Signal, Troposphere, make_pair

    rows = []
    for n_ant in (4, 8):
        for rho in (10.0, 4.0, 2.0):
            with tempfile.TemporaryDirectory() as tmp:
                spec = PairSpec(n_ant=n_ant, n_time=1200, n_scans=2, seed=5,
                                troposphere=Troposphere(step_rad=0.05, drift_rad=0.02,
                                                        ref_offset_scale=0.0),
                                signal=Signal(sigma_ref=1.1 / rho))
                truth = make_pair(Path(tmp), spec)
                out = {}
                for tracker in ("count", "smooth", "antenna"):
                    calibrate_flat(truth.ref_ms, truth.target_ms, tracker=tracker, overwrite=True,
                              no_verdict=True)
                    with pt.table(str(truth.target_ms), ack=False) as t:
                        out[tracker] = residual_rms_deg(truth, t.getcol("PWC_DATA"))
                rows.append((n_ant, rho, out))
                print(n_ant, rho, out, file=sys.stderr, flush=True)
    print("| stations | per-sample SNR | baseline PWC (count) | baseline PWC (smooth) | antenna gains (table = column) | R x thermal, one baseline |")
    print("|---|---|---|---|---|---|")
    for n_ant, rho, out in rows:
        print(f"| {n_ant} | {rho:g} | {out['count']:.1f} deg | {out['smooth']:.1f} deg | "
              f"{out['antenna']:.1f} deg | {np.degrees(230 / 86 / rho / np.sqrt(2)) * np.sqrt(2):.1f} deg |")


if __name__ == "__main__":
    main()
