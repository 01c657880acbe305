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
