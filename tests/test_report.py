"""``hitops report`` on a directory that holds only ``hitops calibrate`` and ``diagnose``
outputs (no recipe, no images), and its refusals.  The recipes' pages are checked in
tests/test_recipes.py and tests/test_recipe_wideband.py, inside the runs they make."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from browser import check_page

HITOPS = Path(sys.executable).parent / "hitops"


def _hitops(*args):
    return subprocess.run([str(HITOPS), *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def test_page_of_calibrate_and_diagnose_outputs(new_demo, tmp_path):
    from hitops.calibrate import calibrate_flat
    from hitops.diagnose import diagnose

    ref, target = new_demo
    report = calibrate_flat(str(ref), str(target), method="pwc,cfpt", tracker="antenna",
                       offset_model="point", no_verdict=True)
    diagnose(str(target), columns="DATA,CFPT_DATA,PWC_DATA", outdir=str(tmp_path / "diagnose"),
             plots="coherence", interval=60.0)
    done = _hitops("report", tmp_path)
    assert done.returncode == 0, done.stderr
    visit = check_page(tmp_path / "index.html", tmp_path / "page.png")
    summary = json.loads((tmp_path / "diagnose" / "summary.json").read_text())
    medians = {col: float(np.median([bl["columns"][col]["coherence_factor"]
                                     for bl in summary["baselines"]]))
               for col in ("DATA", "CFPT_DATA", "PWC_DATA")}
    assert visit.text["verdict"] == (
        f"No images in this directory. Median coherence C(60 s) over {len(summary['baselines'])} "
        f"baselines: DATA {medians['DATA']:.3f}, CFPT_DATA {medians['CFPT_DATA']:.3f}, "
        f"PWC_DATA {medians['PWC_DATA']:.3f}.")
    assert medians["PWC_DATA"] > medians["DATA"]
    html = (tmp_path / "index.html").read_text()
    # the per-station facts of the calibrate report: each station's n0 integers
    n0 = {}
    for solve in report["offset_step"]["antennas"]:
        n0[solve["antenna"]] = n0.get(solve["antenna"], 0) + 1
    assert "sim-230.ms.hitops-calibrate.json" in html and "n0 integers" in html
    for station in n0:
        assert f"<td>{station}</td>" in html
    # the coherence of every baseline and column, as diagnose wrote it
    for bl in summary["baselines"]:
        assert f"<td>{bl['baseline']}</td>" in html
        value = bl["columns"]["PWC_DATA"]["coherence_factor"]
        assert f"{value:.4f}" in html
    # the flag versions of the set, with what made them
    assert "hitops_original" in html and "flags as simulated (hitops)" in html


def test_refusals_are_one_line(tmp_path):
    missing = _hitops("report", tmp_path / "nowhere")
    assert missing.returncode == 2 and "Traceback" not in missing.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    done = _hitops("report", empty)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "nothing to show" in lines[0], done.stderr
    assert list(empty.iterdir()) == []
