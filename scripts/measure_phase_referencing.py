"""The instrumental term with and without --calibrator-field: numbers for docs/solutions.md.

Simulates the packaged scene ``phaseref`` (M87 and the calibrator 3C273 in alternating
scans through one troposphere, per-station instrumental phases, delays and drifts at
both bands, thermal noise), then per variant runs ``hitops calibrate`` (count tracker, PWC) on a
fresh copy of the pair, measures the target field's whole-track coherence per
baseline (|mean V| / the source's 1 Jy over every channel and parallel hand: the
noise averages out, unlike in the mean of unit phasors) and images the
target field with WSClean (the recipes' settings) for a CASA imfit peak.

    python scripts/measure_phase_referencing.py OUTDIR [--scan-gap S] [--seed N]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

#: the target's flux density at 230 GHz in the packaged scene
TARGET_JY = 1.0


def coherence(ms: str, column: str) -> np.ndarray:
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t:
        sel = t.getcol("FIELD_ID") == 0
        a1, a2 = t.getcol("ANTENNA1")[sel], t.getcol("ANTENNA2")[sel]
        data, flag = t.getcol(column)[sel][..., [0, -1]], t.getcol("FLAG")[sel][..., [0, -1]]
    out = []
    for p, q in sorted(set(zip(a1.tolist(), a2.tolist()))):
        v = data[(a1 == p) & (a2 == q)]
        ok = ~flag[(a1 == p) & (a2 == q)] & (np.abs(v) > 0)
        out.append(abs(v[ok].sum()) / ok.sum() / TARGET_JY)
    return np.array(out)


def image_peak(ms: str, column: str, name: str) -> dict:
    from hitops.casa.tasks import imfit

    subprocess.run(["wsclean", "-quiet", "-field", "0", "-data-column", column,
                    "-size", "256", "256", "-scale", "0.005masec", "-niter", "5000",
                    "-threshold", "0.01", "-weight", "natural", "-mgain", "0.5", "-j", "2",
                    "-name", name, ms], check=True, capture_output=True)
    fit = imfit(f"{name}-image.fits", centre_half_width=32, fallback=True,
                fallback_image=f"{name}-dirty.fits", max_abs_peak=5.0, mark_diverged=True,
                detection_snr=5.0, label=Path(name).name)
    return {k: fit.get(k) for k in ("peak", "peak_err", "method")}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("outdir")
    parser.add_argument("--scan-gap", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    from hitops.calibrate import calibrate_flat
    from hitops.simulate import simulate

    out = Path(args.outdir)
    pair = simulate("phaseref", out / "sim", overwrite=True, scan_gap=args.scan_gap,
                    seed=args.seed)
    # the scene's calibrator is resolved: its reference-band model goes too
    variants = {"pwc": {}, "pwc+calibrator": {"calibrator_field": "3C273",
                                              "ref_model_column": "MODEL_DATA"},
                "pwc+n0 point": {"offset_model": "point"}}
    results = {}
    for label, extra in variants.items():
        work = out / label.replace(" ", "-").replace("+", "_")
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        ref, tgt = work / "ref.ms", work / "tgt.ms"
        shutil.copytree(pair["86"], ref)
        shutil.copytree(pair["230"], tgt)
        report = calibrate_flat(str(ref), str(tgt), no_verdict=True, **extra)
        coh = coherence(str(tgt), "PWC_DATA")
        results[label] = {"coherence_min": float(coh.min()),
                          "coherence_median": float(np.median(coh)),
                          "image": image_peak(str(tgt), "PWC_DATA", str(work / "img"))}
        if "phase_referencing" in report:
            results[label]["switches"] = report["phase_referencing"]["methods"]["PWC_DATA"][0][
                "switches"]
        print(label, json.dumps(results[label]), flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    sys.exit(main())
