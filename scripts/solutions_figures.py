"""The measured figures of docs/solutions.md: solution-space FPT through real CASA.

Run ``python scripts/solutions_figures.py [WORKDIR]`` (a few minutes: CASA fringefit
and gaincal on the reference band, applycal on the target for every variant).  The
pair is the tests' (tests/solutions_scene.py: casatools.simulator layout, four
stations, 20 min of 1-s integrations, 86 GHz 16 x 125 MHz -> 227.1 / 229.1 GHz, a
point source behind per-antenna excess paths).  For each table and variant the
target's whole-track coherence after CASA applycal is measured on every
(window, baseline, channel, correlation): the table reports its minimum and median.
The section between the ``figures:solutions`` markers of docs/solutions.md is
replaced.
"""

from __future__ import annotations

import dataclasses
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
DOC = ROOT / "docs" / "solutions.md"
MARK = re.compile(r"(<!-- figures:solutions -->\n).*?(<!-- /figures:solutions -->)", re.S)


def _coherence(ms):
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        data, flag = t.getcol("CORRECTED_DATA"), t.getcol("FLAG")
        key = t.getcol("DATA_DESC_ID") * 10000 + t.getcol("ANTENNA1") * 100 + t.getcol("ANTENNA2")
    values = []
    for k in np.unique(key):
        sel = key == k
        phasor = np.where(flag[sel], 0.0, np.exp(1j * np.angle(data[sel])))
        values.append(np.abs(phasor.sum(axis=0)) / np.maximum((~flag[sel]).sum(axis=0), 1))
    values = np.concatenate([v.ravel() for v in values])
    return float(values.min()), float(np.median(values))


def _apply(ms, table):
    from hitops.casa.runner import run_task

    run_task("applycal", vis=str(ms), gaintable=[str(table)], interp=["linear"],
             applymode="calflag", calwt=[False], flagbackup=False)
    return _coherence(ms)


def _variant(pair, table, out, change_window=None, change_target=None, wrap_counting=True,
             has_rates=True):
    """transfer_table's stages with one piece replaced (a plausible wrong implementation)."""
    from hitops.solutions.read import read_solutions
    from hitops.solutions.transfer import transfer_window, unwrap_window
    from hitops.solutions.write import write_fringe_table
    from solutions_scene import TARGET_CENTRES_HZ

    (window,) = read_solutions(table, pair.ref_ms).windows
    window = change_window(window) if change_window else window
    unwrapped = unwrap_window(window, 60.0, wrap_counting, has_rates)
    targets = [transfer_window(unwrapped, spw, 0, centre, has_rates)
               for spw, centre in enumerate(TARGET_CENTRES_HZ)]
    if change_target:
        targets = [change_target(t, window) for t in targets]
    write_fringe_table(out, pair.target_ms, targets, n_ant=4, overwrite=True)
    return _apply(pair.target_ms, out)


def _row(label, result):
    if isinstance(result, str):
        return f"| {label} | {result} | |"
    return f"| {label} | {result[0]:.5f} | {result[1]:.5f} |"


def _solint_rows(pair, work):
    from hitops.casa.tasks import fringefit
    from hitops.solutions import transfer_table
    from hitops.solutions.errors import SolutionIntervalError

    rows = []
    for solint in (4, 10, 30, 60):
        table = work / f"ref{solint}.fringe"
        fringefit(str(pair.ref_ms), str(table), solint=f"{solint}s", refant="PV,PB", minsnr=3.0,
                  overwrite=True)
        for counted in (True, False):
            out = work / f"t{solint}{counted}.fringe"
            label = f"fringefit {solint} s, {'wraps counted' if counted else 'R*phi (no wrap count)'}"
            try:
                transfer_table(table, pair.ref_ms, pair.target_ms, out, wrap_counting=counted,
                               overwrite=True)
                rows.append(_row(label, _apply(pair.target_ms, out)))
            except SolutionIntervalError as err:
                rows.append(_row(label, f"refused: {str(err).split(':', 1)[1].split(';')[0].strip()}"))
    return rows


def _variant_rows(pair, work):
    from hitops.casa.tasks import gaincal

    table = work / "ref4.fringe"
    rows = [
        _row("fringefit 4 s, phase referred to REF_FREQUENCY (85.0625 GHz)",
             _variant(pair, table, work / "reffreq.fringe",
                      change_window=lambda w: dataclasses.replace(w, ref_freq_hz=85.0625e9))),
        _row("fringefit 4 s, the table's group delay carried instead of u/(2*pi*nu_ref)",
             _variant(pair, table, work / "group.fringe",
                      change_target=lambda t, w: dataclasses.replace(t, delay_s=np.where(t.valid, w.delay_s, 0)))),
        _row("fringefit 4 s, group delay added to u/(2*pi*nu_ref)",
             _variant(pair, table, work / "sum.fringe",
                      change_target=lambda t, w: dataclasses.replace(
                          t, delay_s=t.delay_s + np.where(t.valid, w.delay_s, 0)))),
    ]
    from hitops.solutions import transfer_table

    for kind, extra in (("G", {}), ("T", {"gaintype": "T"})):
        for solint in ("int", "4s", "10s"):
            ref = work / f"ref_{kind}_{solint}"
            gaincal(str(pair.ref_ms), str(ref), solint=solint, refant="PV,PB", calmode="p",
                    minsnr=3.0, minblperant=2, overwrite=True, **extra)
            out = work / f"t_{kind}_{solint}.fringe"
            transfer_table(ref, pair.ref_ms, pair.target_ms, out, overwrite=True)
            rows.append(_row(f"gaincal {kind} Jones, solint {solint}", _apply(pair.target_ms, out)))
    rows.append(_row("gaincal G Jones, solint 4s, written with zero rates (none derived)",
                     _variant(pair, work / "ref_G_4s", work / "zero.fringe", has_rates=False,
                              change_target=lambda t, w: dataclasses.replace(t, rate=0 * t.rate))))
    return rows


def main(argv=None) -> int:
    from solutions_scene import make_solution_pair

    argv = sys.argv[1:] if argv is None else argv
    work = Path(argv[0]) if argv else Path(tempfile.mkdtemp(prefix="hitops-solutions-"))
    pair = make_solution_pair(work)
    rows = _solint_rows(pair, work) + _variant_rows(pair, work)
    table = "\n".join(["| reference table -> target Fringe Jones table | min coherence | median |",
                       "|---|---|---|", *rows])
    print(table)
    text = DOC.read_text()
    DOC.write_text(MARK.sub(lambda m: m.group(1) + table + "\n" + m.group(2), text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
