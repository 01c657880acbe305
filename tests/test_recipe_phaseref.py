"""The phase-referencing recipe (recipes/fpt-phaseref.yml) end to end, under plain
`stimela run`.

Real Stimela, hitops simulate (the packaged `phaseref` scene cut to 30 min: 60-s slews,
each line of sight its own troposphere, a resolved calibrator with its MODEL_DATA,
instrumental terms, thermal noise at the scene's SEFDs), CASA fringefit on the
calibrator's scans, gaincal on the target and applycal (FF+SC), hitops calibrate --method
pwc --calibrator-field, WSClean, CASA imfit, hitops compare and hitops report.  With
thermal noise PWC + the calibrator step must recover the target's peak better than
FF+SC; WSClean's dirty images compare the two columns like for like (a CLEAN that
diverges on FF+SC's data is reported as its brightest dirty pixel, so the fitted table
alone could flatter PWC).  PWC without the step leaves the instrumental term (0.3 ns is
2 x 2 pi across the window) and images at a fraction of the peak (docs/recipes.md).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from test_recipes import run_recipe  # tests/ is on sys.path (rootdir-relative)


@pytest.fixture(scope="module")
def phaseref_run(tmp_path_factory):
    out, _ = run_recipe("fpt-phaseref.yml", tmp_path_factory.mktemp("phaseref"),
                        "duration=1800")
    return out


def _rows(out):
    return {r["label"]: r for r in json.loads((out / "peak-flux.json").read_text())["rows"]}


@pytest.mark.slow
def test_pwc_with_the_step_beats_ffsc(phaseref_run):
    rows = _rows(phaseref_run)
    assert {"raw", "ffsc", "pwc"} <= set(rows)
    pwc, ffsc = rows["pwc"], rows["ffsc"]
    assert pwc["fit"] == "gaussian"
    assert 0.95 <= pwc["recovery"] <= 1.05, pwc
    assert pwc["recovery"] > (ffsc["recovery"] or 0.0) + 0.1, (pwc, ffsc)


@pytest.mark.slow
def test_dirty_images_compare_like_for_like(phaseref_run):
    from astropy.io import fits

    def centre_peak(label):
        image = np.squeeze(fits.getdata(phaseref_run / "images" / f"{label}-dirty.fits"))
        ny, nx = image.shape
        return float(image[ny // 2 - 2:ny // 2 + 3, nx // 2 - 2:nx // 2 + 3].max())

    pwc, ffsc, raw = centre_peak("pwc"), centre_peak("ffsc"), centre_peak("raw")
    assert pwc > ffsc + 0.1 and ffsc > raw, (pwc, ffsc, raw)
    assert 0.9 < pwc < 1.05, pwc


@pytest.mark.slow
def test_the_step_ran_on_the_resolved_model_and_the_page_exists(phaseref_run):
    report = json.loads((phaseref_run / "sim-230.ms.hitops-calibrate.json").read_text())
    step = report["phase_referencing"]
    assert step["calibrator_field"] == "3C273" and step["calibrator_model"] == "MODEL_DATA"
    window = step["methods"]["PWC_DATA"][0]
    assert window["integers"]["rule"] == "delay"
    # 30 min of a 5-min cycle: 6 calibrator scans, every one solved
    assert len(window["scans"]) == 6
    page = (phaseref_run / "index.html").read_text()
    assert "PWC" in page and "FF+SC" in page
    # the page shows what the step did: its model, its rule and every antenna's terms
    assert "Phase referencing: PWC_DATA" in page and "model: MODEL_DATA" in page
    assert "by the delay rule" in page and "6 calibrator scans" in page
    stations = {a for a in window["antennas"]}
    assert all(f"<td>{s}</td>" in page for s in stations) and len(stations) == 5
