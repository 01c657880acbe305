"""The forecast's slip model against a direct simulation (hitops simulate + hitops calibrate).

One baseline, one weather (a date of the tables), a flux low enough for slips
to happen: ``hitops simulate`` writes the pair with the MERRA-2 weather,
``hitops calibrate --tracker count`` (the paper's naive PWC) writes PWC_DATA,
and the wrap count it applied is read back from PWC_DATA / DATA
(= exp(-i (R phi_cal - 2 pi eps n)), which gives n modulo 43 for R = 230/86).
Measured: the number of steps where the count error against the simulator's
truth changes. Predicted: the sum over the track's steps of the forecast
model's per-step probability, with the per-sample SNR from SIGMA and the
coherence time and elevation from the truth file.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from . import model
from ..io import tables


def _read(ms, *cols):
    with tables.main_table(str(ms)) as t:
        return [t.getcol(c) for c in cols]


def direct_check(codes, outdir, date="2018-04-10", start="2018-04-10T00:00:00", duration=3600.0,
                 target_rho=2.6, seed=1) -> dict:
    from ..calibrate import OutputOptions, TrackingOptions, calibrate
    from ..simulate import simulate
    from ..simulate.scene import load_scene_mapping

    outdir = Path(outdir)
    scene, _ = load_scene_mapping("paper")
    scene["weather"] = {"source": "merra2", "date": date}
    scene["stations"] = [{"code": c, "elevation_limit": 10} for c in codes]
    scene["observation"].update({"start": start, "duration": duration})
    scene["corruptions"]["seed"] = seed
    scene["corruptions"].pop("airmass_elevation_floor", None)
    # first pass: the SNR at 1.1 Jy, then scale the 86 GHz flux to the target median rho
    probe = simulate(scene, outdir / "probe", overwrite=True, no_noise=True)
    (sigma,) = _read(probe["86"], "SIGMA")
    flux = target_rho * float(np.median(sigma[:, 0]))
    scene["source"]["flux"] = {"86": flux, "230": 1.0}
    paths = simulate(scene, outdir / "sim", overwrite=True, save_truth=True)
    calibrate(str(paths["86"]), str(paths["230"]), tracking=TrackingOptions(tracker="count"),
              output=OutputOptions(method="pwc", overwrite=True))
    truth = np.load(paths["truth"])
    ref, sig, t86 = _read(paths["86"], "DATA", "SIGMA", "TIME")
    pwc, dat = _read(paths["230"], "PWC_DATA", "DATA")
    ratio = 230.0 / 86.0
    measured = predicted = 0.0
    for c in range(ref.shape[2]):                       # RR and LL: independent noise
        phi_cal = np.angle(ref[:, 0, c])
        z = (pwc[:, 0, c] / dat[:, 0, c]) * np.exp(1j * ratio * phi_cal)
        k = np.round(np.angle(z) / (2 * np.pi / 43)).astype(np.int64) % 43
        n_mod = (3 * k) % 43                            # 29^-1 = 3 (mod 43)
        step = (np.diff(n_mod) + 21) % 43 - 21          # count changes, |step| <= 21
        n_meas = np.concatenate([[0], np.cumsum(step)])
        ti = np.searchsorted(truth["time"], t86)
        true_phase = truth["phase_86"][0, ti] - truth["phase_86"][1, ti]
        # the lobe of the unwrapped measured phase (phi - 2 pi n) about the true phase:
        # a failure is a step where it changes (a noise excursion across +-pi that the
        # count follows is no failure)
        lobe = np.round((phi_cal - 2 * np.pi * n_meas - true_phase) / (2 * np.pi))
        measured += float(np.count_nonzero(np.diff(lobe)))
        rho = flux / sig[:, c]
        tc = truth["coherence_time_series"][:, ti].astype(np.float64) * (86.0 / 230.0) ** (-1.2)
        sin_el = np.sin(truth["elevation"][:, ti])
        tc_local = tc * np.clip(sin_el, 1e-3, 1) ** 0.6
        dt = float(np.median(np.diff(t86)))
        step_var = (dt / tc_local[0]) ** (5 / 3) + (dt / tc_local[1]) ** (5 / 3)
        p = model.naive_failure_probability(0.5 * (rho[1:] + rho[:-1]), np.sqrt(step_var[1:]))
        predicted += float(np.sum(p))
    return {"baseline": "-".join(codes), "date": date, "duration_s": duration,
            "flux_86_jy": flux, "median_rho": float(np.median(flux / sig[:, 0])),
            "measured_failures": measured, "predicted_failures": predicted,
            "poisson_sigma": math.sqrt(max(predicted, 1.0)),
            "z": (measured - predicted) / math.sqrt(max(predicted, 1.0))}
