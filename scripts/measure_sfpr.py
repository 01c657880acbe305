"""How often the calibrator step finds each scan's integer right (docs/solutions.md, "The
instrumental term"): window width (channels of 125 MHz), thermal noise, slew.

    python scripts/measure_sfpr.py OUTDIR [--chans 8 16 32] [--noise 0 0.1 0.25]
                                          [--slews 60 90] [--duration 1800]

Per case the scene of hitops/testing/phaseref_scene.py is laid out twice by
casatools.simulator, without and with noise (the same troposphere, instrument and sky);
calibrate --calibrator-field runs on both; the noise-free run's integers (checked by its
target coherence, 1.000 on every series) are the truth the noisy run's are counted against.
The too-faint refusal is turned off here so that every decision is counted; the table says
whether the step would have refused.  Prints one markdown row per case.
"""

from __future__ import annotations

import argparse
import logging
import shutil
from pathlib import Path

import numpy as np

from hitops.calibrate import calibrate_flat
from hitops.calibrate.phaseref import apply as target_side
from hitops.calibrate.phaseref import solve as calibrator_side
from hitops.errors import InputError
from hitops.testing.phaseref_scene import PhaserefSpec, make_phaseref_pair, target_coherence

#: sigma per visibility part -> SEFD (Jy) of both stations: sigma = SEFD / sqrt(2 dnu dt) / 0.88
SEFD_PER_SIGMA = 0.88 * np.sqrt(2 * 125e6 * 4.0)


def _run(pair, workdir: Path):
    """(calibrator integers, target integers, coherence, would refuse) of one run."""
    seen = {}
    cal_found, tgt_found = calibrator_side.calibrator_integers, target_side.target_integers
    checked = calibrator_side.check_decided

    def spy_cal(*args):
        seen["cal"] = cal_found(*args)
        try:
            checked(seen["cal"], list(range(seen["cal"].integers.shape[0])),
                    [str(b) for b in range(seen["cal"].integers.shape[1])], "CAL", 0)
            seen["refuse"] = False
        except InputError:
            seen["refuse"] = True
        return seen["cal"]

    def spy_tgt(*args):
        seen["tgt"] = tgt_found(*args)
        return seen["tgt"]

    calibrator_side.calibrator_integers, target_side.target_integers = spy_cal, spy_tgt
    calibrator_side.check_decided = lambda *a: None
    try:
        shutil.rmtree(workdir, ignore_errors=True)
        workdir.mkdir(parents=True)
        for name in ("ref.ms", "target.ms"):
            shutil.copytree(Path(pair.ref_ms).parent / name, workdir / name)
        calibrate_flat(str(workdir / "ref.ms"), str(workdir / "target.ms"), method="pwc",
                  no_verdict=True, calibrator_field="CAL", ref_model_column="MODEL_DATA")
    finally:
        calibrator_side.calibrator_integers, target_side.target_integers = cal_found, tgt_found
        calibrator_side.check_decided = checked
    return seen["cal"], seen["tgt"], target_coherence(workdir / "target.ms", "PWC_DATA"), \
        seen["refuse"]


def measure(out: Path, n_chan: int, noise: float, slew: float, duration: float) -> str:
    base = PhaserefSpec(n_chan=n_chan, slew_s=slew, duration_s=duration)
    truth_pair = make_phaseref_pair(out / "truth", base)
    cal_t, tgt_t, coh_t, _ = _run(truth_pair, out / "truth-run")
    if noise > 0:
        pair = make_phaseref_pair(out / "noisy", PhaserefSpec(
            n_chan=n_chan, slew_s=slew, duration_s=duration, noise_jy=noise))
        cal_n, tgt_n, coh_n, refuse = _run(pair, out / "noisy-run")
    else:
        cal_n, tgt_n, coh_n, refuse = cal_t, tgt_t, coh_t, False
    measured = np.isfinite(cal_t.margin)
    cal_right = (cal_n.integers == cal_t.integers)[measured].mean()
    decided = tgt_t.valid & ~tgt_n.undecided
    tgt_right = (tgt_n.integers == tgt_t.integers)[decided].mean()
    sefd = noise * SEFD_PER_SIGMA
    return (f"| {n_chan * 125 / 1000:g} GHz | {n_chan} | {noise:g} ({sefd:.0f} Jy) | {slew:g} s "
            f"| {cal_right:.3f} ({measured.sum()}) | {tgt_right:.3f} ({decided.sum()} of "
            f"{tgt_t.valid.sum()}) | {'yes' if refuse else 'no'} | {coh_n.min():.3f} / "
            f"{np.median(coh_n):.3f} | {coh_t.min():.4f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--chans", type=int, nargs="+", default=[8, 16, 32])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.1, 0.25])
    parser.add_argument("--slews", type=float, nargs="+", default=[60.0, 90.0])
    parser.add_argument("--duration", type=float, default=1800.0)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    print("| window | channels | noise per part (SEFD) | slew | calibrator integers right "
          "(decided) | target integers right (taken of measured) | step refuses | target "
          "coherence min / median | noise-free min |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n_chan in args.chans:
        for noise in args.noise:
            for slew in args.slews:
                print(measure(args.out / f"c{n_chan}-n{noise:g}-s{slew:g}", n_chan, noise, slew,
                              args.duration), flush=True)


if __name__ == "__main__":
    main()
