"""The wideband recipe (recipes/fpt-wideband.yml) end to end, under plain `stimela run`.

Real Stimela, hitops simulate (the packaged `wideband` scene: two 2-GHz windows of
16 channels at 230 GHz, one at 86 GHz), CASA fringefit/gaincal/applycal, hitops
calibrate twice (one ratio per channel -> PWC_DATA; one ratio per window,
--average-channels -> PWC_WIN_DATA), hitops diagnose, WSClean over all channels,
CASA imfit and hitops compare.  What is checked comes from outside the code under
test where it can: the scene's own excess paths (the simulator's truth) predict how
much one ratio per window decorrelates each baseline, 2*pi*(nu_k - nu_window)*dL(t)/c
on channel k, and WSClean's dirty images compare the two columns like for like.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from test_recipes import RECIPES, stimela  # tests/ is on sys.path (rootdir-relative)

SPEED_OF_LIGHT = 299792458.0
LABELS = ("raw", "ffsc", "pwcwin", "pwc")


@pytest.fixture(scope="module")
def wideband_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("wideband")
    out = work / "out"
    # the coherence plots only: the waterfalls add a minute and nothing checked here
    args = ("run", str(RECIPES / "fpt-wideband.yml"), f"dir={out}", "plots=coherence")
    done = stimela(*args, cwd=work)
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-3000:]
    return work, out, args


def _rows(out):
    return {r["label"]: r for r in json.loads((out / "peak-flux.json").read_text())["rows"]}


@pytest.mark.slow
def test_wideband_table_has_one_ratio_per_window_beside_per_channel_pwc(wideband_run):
    _, out, _ = wideband_run
    rows = _rows(out)
    assert set(LABELS) <= set(rows)
    assert rows["pwcwin"]["method"] == "PWC, one ratio per window (PWC_WIN_DATA)"
    pwc, ffsc, window = rows["pwc"], rows["ffsc"], rows["pwcwin"]
    assert pwc["fit"] == "gaussian" and ffsc["fit"] == "gaussian"
    assert 0.95 <= pwc["recovery"] <= 1.05
    assert pwc["recovery"] > ffsc["recovery"]
    # one ratio per window: whatever the fit (a CLEAN that diverged on it is reported
    # as the dirty image's brightest pixel), never above per-channel PWC
    window_recovery = window["recovery"] if window["recovery"] is not None else 0.0
    assert pwc["recovery"] >= window_recovery
    text = (out / "peak-flux.md").read_text()
    assert "PWC, one ratio per window (PWC_WIN_DATA)" in text and "PWC (PWC_DATA)" in text


@pytest.mark.slow
def test_dirty_images_compare_the_two_columns_like_for_like(wideband_run):
    """Both columns' dirty images (same data, weights and grid; no CLEAN to diverge):
    per-channel PWC holds more of the source at the phase centre."""
    from astropy.io import fits

    _, out, _ = wideband_run

    def centre_peak(label):
        image = np.squeeze(fits.getdata(out / "images" / f"{label}-dirty.fits"))
        ny, nx = image.shape
        return float(image[ny // 2 - 2:ny // 2 + 3, nx // 2 - 2:nx // 2 + 3].max())

    pwc, window = centre_peak("pwc"), centre_peak("pwcwin")
    assert pwc > window + 0.05, (pwc, window)
    assert 0.85 < pwc < 1.05


@pytest.mark.slow
def test_one_ratio_per_window_loses_what_the_excess_path_predicts(wideband_run, tmp_path):
    """Per baseline, the table's all-channel coherence of PWC_WIN_DATA equals per-channel
    PWC's times the decorrelation the scene's excess path predicts for one ratio per
    window (the simulator's truth, not calibrate's output), to 0.02."""
    from hitops.simulate import simulate

    _, out, _ = wideband_run
    coherence = json.loads((out / "peak-flux.json").read_text())["coherence"]
    assert coherence["measure"] == "time and all channels averaged together"
    by_baseline = {b["baseline"]: b for b in coherence["baselines"]}
    # the same scene and seed again, for its truth (the excess path per station)
    simulate("wideband", outdir=str(tmp_path), save_truth=True, overwrite=True)
    truth = np.load(tmp_path / "sim-truth.npz")
    path, time, stations = truth["path_m"], truth["time"], [str(s) for s in truth["stations"]]
    chan_freq = truth["chan_freq_230"]
    offsets = (chan_freq - chan_freq.mean(axis=1, keepdims=True)).ravel()   # nu_k - nu_window
    minute = ((time - time[0]) // coherence["interval_s"]).astype(int)
    worst = 1.0
    for p in range(len(stations)):
        for q in range(p + 1, len(stations)):
            row = by_baseline[f"{stations[p]}-{stations[q]}"]
            residual = 2 * np.pi * offsets[None, :] * (path[p] - path[q])[:, None] / SPEED_OF_LIGHT
            phasors = np.exp(1j * residual)
            slope_c = np.mean([abs(phasors[minute == m].mean()) for m in np.unique(minute)])
            predicted = row["pwc"] * slope_c
            assert row["pwcwin"] == pytest.approx(predicted, abs=0.02), (row["baseline"], slope_c)
            assert row["pwc"] >= row["pwcwin"]
            worst = min(worst, row["pwcwin"])
    # the scene shows it: radians at the windows' edges on the longest path differences
    assert worst < 0.75


@pytest.mark.slow
def test_wideband_rerun_skips_every_step_when_fresh(wideband_run):
    work, out, args = wideband_run
    before = {p: p.stat().st_mtime_ns for p in
              [out / "peak-flux.json", out / "calibrate-window.json", out / "images" / "pwc-imfit.json"]}
    done = stimela(*args, cwd=work)
    assert done.returncode == 0, done.stdout[-4000:]
    # Stimela's lines wrap at the terminal's width: join them, then one chunk per step
    log = re.sub(r"\s+", " ", done.stdout)
    chunks = [(m.group(1), m.group(2)) for m in
              re.finditer(r"processing step '([\w-]+)'(.*?)(?=processing step|$)", log)]
    steps = ("simulate", "fringefit", "gaincal", "applycal", "calibrate", "calibrate_window",
             "diagnose", "image", "imfit", "compare")
    assert set(steps) <= {name for name, _ in chunks}, chunks
    for name, text in chunks:
        assert name not in steps or "skipping this step" in text, name
    assert sum(name == "image" for name, _ in chunks) == len(LABELS)
    assert "fringefit(vis=" not in log and "imfit(imagename=" not in log
    assert {p: p.stat().st_mtime_ns for p in before} == before


@pytest.mark.slow
def test_wideband_page_in_a_real_browser_after_the_rerun(wideband_run):
    from browser import check_page, page_numbers_equal_table

    work, out, _ = wideband_run
    visit = check_page(out / "index.html", work / "wideband-page.png")
    page_numbers_equal_table(visit, out / "peak-flux.json")
    srcs = [src for src, _ in visit.images]
    assert sorted(s for s in srcs if s.startswith("report/image-")) == sorted(
        f"report/image-{label}.png" for label in LABELS)
    # the page of the rerun (the test before) says every step was up to date, and why
    steps = visit.text["steps"]
    for name in ("simulate", "fringefit", "calibrate_window", "diagnose", "images", "compare"):
        assert f"{name} up to date" in steps, steps
    # wideband: every baseline and column per window, as diagnose measured it
    summary = json.loads((out / "diagnose" / "summary.json").read_text())
    html = (out / "index.html").read_text()
    spectral = summary["spectral"]
    assert len(spectral["windows"]) == 2 and "id='spectral-table'" in html
    for col, entry in spectral["columns"].items():
        for values in entry["baselines"].values():
            for value in values["windows"]:
                assert f"{value:.4f}" in html
