"""hitops compare: fractional peak-flux recovery tables from imfit results."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

from hitops.compare import PAPER, compare, recovery
from hitops.errors import InputError, OutputExistsError


def write_fit(path, label, peak, peak_err, method="gaussian"):
    path.write_text(json.dumps({"label": label, "image": f"{label}-image.fits",
                                "method": method, "peak": peak, "peak_err": peak_err}))
    return str(path)


def test_recovery_is_peak_over_input_with_propagated_error():
    value, err = recovery(0.93, 0.0046, 1.0)
    assert value == pytest.approx(0.93)
    assert err == pytest.approx(0.0046)
    # the paper's 86 GHz flux: 1.1 Jy; a relative input error adds in quadrature
    value, err = recovery(1.0, 0.01, 1.1, 0.011)
    assert value == pytest.approx(1.0 / 1.1)
    assert err == pytest.approx((1.0 / 1.1) * (0.01 ** 2 + 0.01 ** 2) ** 0.5)
    assert type(value) is float and type(err) is float


def test_recovery_rejects_bad_input_peak():
    with pytest.raises(InputError, match="input peak"):
        recovery(1.0, 0.1, 0.0)


def test_compare_writes_three_tables(tmp_path):
    fits = [write_fit(tmp_path / "ffsc.json", "ffsc", 0.868, 0.0045),
            write_fit(tmp_path / "pwc.json", "pwc", 0.965, 0.0046),
            write_fit(tmp_path / "raw.json", "raw", 0.05, 0.02, method="max-pixel")]
    out = tmp_path / "out"
    payload = compare(",".join(fits), input_peak=1.0, reference="paper", outdir=str(out))
    rows = {r["label"]: r for r in payload["rows"]}
    assert rows["pwc"]["recovery"] == pytest.approx(0.965)
    assert rows["pwc"]["paper_recovery"] == PAPER["recovery"]["pwc"][0]
    assert rows["raw"]["paper_recovery"] is None
    with open(out / "peak-flux.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["label"] for r in table] == ["ffsc", "pwc", "raw"]
    assert float(table[1]["recovery_err"]) == pytest.approx(0.0046)
    md = (out / "peak-flux.md").read_text()
    assert "PWC (PWC_DATA)" in md and "0.9650 ± 0.0046" in md and "0.965 ± 0.0046" in md
    assert "max-pixel" in md  # a fallback measurement is marked as such
    assert json.loads((out / "peak-flux.json").read_text())["rows"][0]["label"] == "ffsc"


def test_compare_refuses_to_overwrite_and_checks_labels(tmp_path):
    fit = write_fit(tmp_path / "a.json", "pwc", 0.9, 0.01)
    compare(fit, outdir=str(tmp_path))
    with pytest.raises(OutputExistsError, match="--overwrite"):
        compare(fit, outdir=str(tmp_path))
    compare(fit, outdir=str(tmp_path), overwrite=True)
    with pytest.raises(InputError, match="one label per file"):
        compare(fit, labels="a,b", outdir=str(tmp_path), name="x")
    with pytest.raises(InputError, match="more than once"):
        compare(f"{fit},{fit}", outdir=str(tmp_path), name="y")
    with pytest.raises(InputError, match="does not exist"):
        compare(str(tmp_path / "missing.json"), outdir=str(tmp_path), name="z")


def test_coherence_summary_from_diagnose_layout(tmp_path):
    # the layout of `hitops diagnose` summary.json (baselines -> columns -> coherence_factor)
    summary = {"interval_s": 60.0, "baselines": [
        {"baseline": "AP-PV", "columns": {"DATA": {"coherence_factor": 0.3},
                                          "CORRECTED_DATA": {"coherence_factor": 0.8},
                                          "PWC_DATA": {"coherence_factor": 0.96}}},
        {"baseline": "PV-PB", "columns": {"DATA": {"coherence_factor": 0.4},
                                          "CORRECTED_DATA": {"coherence_factor": 0.9},
                                          "PWC_DATA": {"coherence_factor": 0.99}}},
    ]}
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(summary))
    fit = write_fit(tmp_path / "pwc.json", "pwc", 0.97, 0.005)
    payload = compare(fit, coherence=str(path), reference="paper", outdir=str(tmp_path))
    coh = payload["coherence"]
    assert coh["columns"] == ["raw", "ffsc", "pwc"]
    stats = coh["stats"]
    assert stats["pwc_ge_ffsc_every_baseline"] is True
    assert stats["pwc_over_ffsc_mean_pct"] == pytest.approx(100 * ((0.96 / 0.8 + 0.99 / 0.9) / 2 - 1))
    assert stats["ffsc_min"] == 0.8 and stats["pwc_max"] == 0.99
    assert "| AP-PV | 0.300 | 0.800 | 0.960 | 20.0% |" in (tmp_path / "peak-flux.md").read_text()


def test_cli_runs_from_the_schema(tmp_path):
    fit = write_fit(tmp_path / "pwc.json", "pwc", 0.97, 0.005)
    cmd = [sys.executable, "-m", "hitops.cli", "compare", fit, "--outdir", str(tmp_path / "o"),
           "--input-peak", "0.5"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    rows = json.loads((tmp_path / "o" / "peak-flux.json").read_text())["rows"]
    assert rows[0]["recovery"] == pytest.approx(1.94)
    again = subprocess.run(cmd, capture_output=True, text=True)
    assert again.returncode == 2 and "--overwrite" in again.stderr


# ---------------------------------------------------------------------------
# issue 17: a source-less image and a diverged CLEAN are said as such

def test_no_source_and_diverged_rows_are_not_presented_as_numbers(tmp_path):
    from hitops.compare.table import text_summary

    raw = tmp_path / "raw.json"
    raw.write_text(json.dumps({"label": "raw", "method": "no-source", "peak": None,
                               "peak_err": None, "brightest": 0.0209, "rms": 0.0096,
                               "snr": 2.2, "reason": "no source: ..."}))
    cfpt = tmp_path / "cfpt.json"
    cfpt.write_text(json.dumps({"label": "cfpt", "method": "max-pixel", "peak": 0.12,
                                "peak_err": 0.07, "diverged": True,
                                "fallback_image": "images/cfpt-dirty.fits",
                                "reason": "imfit peak -3.4e+21 Jy/beam ... diverged"}))
    fits = [str(raw), write_fit(tmp_path / "ffsc.json", "ffsc", 0.914, 0.0012), str(cfpt),
            write_fit(tmp_path / "pwc.json", "pwc", 0.995, 0.0012)]
    payload = compare(",".join(fits), outdir=str(tmp_path / "out"))
    rows = {r["label"]: r for r in payload["rows"]}
    assert rows["raw"]["recovery"] is None and rows["raw"]["peak_jy"] is None
    assert rows["raw"]["fit"] == "no-source"
    assert "CLEAN diverged" in rows["cfpt"]["note"]
    md = (tmp_path / "out" / "peak-flux.md").read_text()
    raw_line = next(l for l in md.splitlines() if l.startswith("| raw"))
    assert "no source" in raw_line and "0.0209" not in raw_line
    with open(tmp_path / "out" / "peak-flux.csv") as fh:
        assert next(r for r in csv.DictReader(fh) if r["label"] == "raw")["recovery"] == ""
    text = text_summary(payload)
    lines = text.splitlines()
    assert "no source" in next(l for l in lines if "raw (DATA)" in l)
    assert "CLEAN diverged" in next(l for l in lines if "CFPT" in l)
    assert "0.995 ± 0.001" in next(l for l in lines if "PWC (PWC_DATA)" in l)


def test_text_summary_has_the_coherence_table_and_the_paper(tmp_path):
    from hitops.compare.table import text_summary

    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"interval_s": 60.0, "baselines": [
        {"baseline": "AP-PV", "columns": {"DATA": {"coherence_factor": 0.3},
                                          "CORRECTED_DATA": {"coherence_factor": 0.9},
                                          "PWC_DATA": {"coherence_factor": 0.99}}},
        {"baseline": "PV-PB", "columns": {"DATA": {"coherence_factor": 0.2},
                                          "CORRECTED_DATA": {"coherence_factor": 0.8},
                                          "PWC_DATA": {"coherence_factor": 0.96}}}]}))
    fit = write_fit(tmp_path / "pwc.json", "pwc", 0.95, 0.01)
    payload = compare(fit, coherence=str(summary), reference="paper", outdir=str(tmp_path))
    text = text_summary(payload)
    assert "Coherence C(60 s) per baseline" in text
    assert "PV-PB" in text and "+20.0%" in text
    assert "[0.965]" in text and "paper:" in text
    assert max(len(l) for l in text.splitlines()) <= 100


def test_figures_scale_each_panel_and_show_a_diverged_clean_as_dirty(tmp_path):
    import matplotlib.image as mpimg
    import numpy as np

    from hitops.casa_env import ensure_casa_offline
    from hitops.compare.figures import image_panels, pick_image

    ensure_casa_offline()   # before casatools is first imported
    casatools = pytest.importorskip("casatools")

    def fits(name, peak):
        n = 64
        x, y = np.mgrid[:n, :n]
        pixels = peak * np.exp(-((x - 32) ** 2 + (y - 32) ** 2) / 18.0)
        cs = casatools.coordsys()
        csys = cs.newcoordsys(direction=True)
        csys.setincrement([-1e-10, 1e-10], "direction")
        ia = casatools.image()
        ia.fromarray(outfile=str(tmp_path / f"{name}.im"), pixels=pixels,
                     csys=csys.torecord(), overwrite=True)
        ia.tofits(str(tmp_path / f"{name}.fits"), overwrite=True, velocity=False)
        ia.done()
        csys.done()
        cs.done()

    fits("ffsc-image", 0.9)
    fits("cfpt-image", 3e21)      # diverged, still under its usual name
    fits("cfpt-dirty", 0.12)
    fits("raw-image.diverged", 1e20)  # renamed by the imfit step
    fits("raw-dirty", 0.05)
    assert pick_image(str(tmp_path), "ffsc") == (str(tmp_path / "ffsc-image.fits"), "restored")
    assert pick_image(str(tmp_path), "cfpt")[1] == "dirty: CLEAN diverged"
    assert pick_image(str(tmp_path), "raw") == (str(tmp_path / "raw-dirty.fits"),
                                                "dirty: CLEAN diverged")
    out = image_panels(str(tmp_path), str(tmp_path / "p.png"), ["raw", "ffsc", "cfpt"],
                       half_width=16)
    pixels = mpimg.imread(out)
    # every panel scaled by itself: each has bright (yellow) pixels at its centre
    width = pixels.shape[1]
    for k in range(3):
        panel = pixels[:, k * width // 3:(k + 1) * width // 3, :3]
        bright = (panel[..., 0] > 0.9) & (panel[..., 1] > 0.8) & (panel[..., 2] < 0.6)
        assert bright.sum() > 20, f"panel {k} has no bright pixels"
