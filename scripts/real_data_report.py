"""Figures and tables of docs/real-data.md: HITOPS on the EHT's public M87 data (2017 April 5).

Usage (from the repository root, with the project's environment):

    .venv/bin/python scripts/real_data_report.py [--workdir out/real-data]

Imports both bands of tests/data/eht2017-m87 with CASA importuvfits, runs
``hitops calibrate`` with each method and tracker, measures what each did to the
target band's closure phases and coherence, compares the verdict with the
measurement, and runs ``hitops diagnose`` for the C(T) plots (copied to
docs/figures/real-data-*.png).  Prints the markdown tables it measured.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "eht2017-m87"
LO = DATA / "SR1_M87_2017_095_lo_hops_netcal_StokesI.uvfits"
HI = DATA / "SR1_M87_2017_095_hi_hops_netcal_StokesI.uvfits"
HITOPS = Path(sys.executable).with_name("hitops")

RUNS = [("CFPT_DATA", "cfpt", "count"), ("PWC_DATA", "pwc", "count"),
        ("PWC_SMOOTH", "pwc", "smooth"), ("PWC_ANTENNA", "pwc", "antenna")]


def importuvfits(fits: Path, ms: Path) -> Path:
    code = ("from hitops.casa_env import ensure_casa_offline; ensure_casa_offline(); "
            "from casatasks import importuvfits; import sys; "
            "importuvfits(fitsfile=sys.argv[1], vis=sys.argv[2])")
    subprocess.run([sys.executable, "-c", code, str(fits), str(ms)], check=True,
                   capture_output=True)
    return ms


def closures(ms: Path, column: str, flag: np.ndarray):
    """{(time, p, q, r): closure phase} of RR over triangles of unflagged baselines."""
    from casacore import tables as pt

    from hitops.diagnose.closures import row_closures

    with pt.table(str(ms), ack=False) as t:
        time, a1, a2 = t.getcol("TIME"), t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        vis = t.getcol(column)[:, 0, 0]
    return row_closures(time, a1, a2, vis, ~flag[:, 0, 0] & (np.abs(vis) > 0))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=str(ROOT / "out" / "real-data"))
    args = parser.parse_args()
    work = Path(args.workdir)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    ref, tgt = importuvfits(LO, work / "lo.ms"), importuvfits(HI, work / "hi.ms")

    from casacore import tables as pt

    from hitops.calibrate import calibrate_flat
    from hitops.calibrate import verdict as V
    from hitops.diagnose.closures import closure_change

    reports = {}
    for column, method, tracker in RUNS:
        reports[column] = calibrate_flat(str(ref), str(tgt), method=method, tracker=tracker,
                                    output_column=column, no_verdict=column != "PWC_DATA")
    with pt.table(str(tgt), ack=False) as t:
        flag = t.getcol("FLAG")
    before = closures(tgt, "DATA", flag)
    print("| column | method, tracker | triangles x times | median abs closure change (rad) | max (rad) |")
    print("|---|---|---|---|---|")
    for column, method, tracker in RUNS:
        diff = closure_change(before, closures(tgt, column, flag))
        print(f"| {column} | {method}, {tracker} | {diff.size} | {np.median(diff):.3g} | "
              f"{diff.max():.3g} |")

    verdict = V.Verdict(interval=60.0, ratio=reports["PWC_DATA"]["ratio"],
                        baselines=[V.BaselineVerdict(**e) for e in
                                   reports["PWC_DATA"]["verdict"]["baselines"]])
    V.measure(verdict, str(tgt), "DATA", "PWC_DATA")
    print()
    print("| baseline | predicted change of C(60 s) | measured | verdict | R x sigma_ref (deg) | "
          "SIGMA / measured scatter, reference |")
    print("|---|---|---|---|---|---|")
    for e in verdict.baselines:
        if e.correlation != "RR":
            continue
        print(f"| {e.baseline} | {100 * e.predicted_change:+.1f}% | "
              f"{100 * e.measured_change:+.1f}% | {e.verdict} | "
              f"{np.degrees(verdict.ratio * e.sigma_ref_rad):.0f} | "
              f"{1 / e.sigma_ratio_ref if e.sigma_ratio_ref else float('nan'):.2f} |")
    print()
    print(V.summary(verdict))
    print("reference closure check:", reports["PWC_DATA"]["verdict"]["reference_closure"])

    diag = work / "diagnose"
    subprocess.run([str(HITOPS), "diagnose", str(tgt), "--columns",
                    "DATA,PWC_DATA,PWC_ANTENNA", "--outdir", str(diag), "--plots", "coherence"],
                   check=True, capture_output=True)
    figures = ROOT / "docs" / "figures"
    # the overview and three baselines (weak, strong, long) are enough for the page
    keep = {"coherence-all.png", "coherence-AZ-JC.png", "coherence-AP-PV.png", "coherence-JC-LM.png"}
    for png in sorted(p for p in (diag / "plots").glob("*.png") if p.name in keep):
        shutil.copy(png, figures / f"real-data-{png.name}")
        print("figure:", figures / f"real-data-{png.name}")
    print((diag / "coherence-table.txt").read_text())


if __name__ == "__main__":
    main()
