"""The verdict: does FPT raise or lower the target's coherence, predicted before the fact?

Checked against what calibrate then does (C(T) of PWC_DATA against DATA) on two
kinds of data with opposite answers:

* a simulated scene with troposphere (hitops simulate demo): FPT must help everywhere,
  read whole (1650 times) and, 3 h of 1 s integrations, from blocks of times spread
  over the track (hitops/calibrate/verdict_sample.py);
* the EHT's public M87 data, fringe fitted per band already: FPT must hurt, by about
  the transferred reference noise, and the source's structure at the reference band
  must be flagged for the baseline methods.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate import verdict as V
from hitops.simulate import simulate

pytestmark = pytest.mark.slow


def predicted_and_measured(ref, tgt, **kw):
    report = calibrate_flat(str(ref), str(tgt), method="pwc", overwrite=True, **kw)
    verdict = V.Verdict(interval=report["verdict"]["interval_s"], ratio=report["ratio"],
                        baselines=[V.BaselineVerdict(**e) for e in report["verdict"]["baselines"]])
    V.measure(verdict, str(tgt), "DATA", "PWC_DATA")
    return report, verdict


def test_simulated_troposphere_fpt_helps_and_the_verdict_says_so(tmp_path):
    out = simulate("demo", tmp_path, seed=3)
    report, verdict = predicted_and_measured(out["86"], out["230"])
    summary = V.summary(verdict)
    assert summary["measured"] >= 10
    assert all(e.measured_change > 0.05 for e in verdict.baselines)
    assert summary["help"] == summary["measured"] == summary["verdict_agrees"]
    # the size too, within a third of the measured change
    rel = [abs(e.predicted_change - e.measured_change) / e.measured_change for e in verdict.baselines]
    assert np.median(rel) < 0.33
    assert report["verdict"]["reference_closure"]["consistent_with_zero"]
    sampled = report["verdict"]["sampled"]
    assert sampled["times_read"] == sampled["times"] == 1650   # 1 h of 2 s, less the gaps


def test_sampled_verdict_on_a_long_track_has_the_same_sign_and_size(tmp_path, caplog):
    """A track long enough to be sampled: the prediction from the blocks against what the
    run then does over the whole track."""
    out = simulate("demo", tmp_path, seed=3, duration=3 * 3600, integration=1)
    with caplog.at_level("INFO", logger="hitops"):
        report, verdict = predicted_and_measured(out["86"], out["230"])
    sampled = report["verdict"]["sampled"]
    assert sampled["times"] == 9840 and sampled["times_read"] < sampled["times"] / 2
    summary = V.summary(verdict)
    assert summary["measured"] >= 10
    assert summary["help"] == summary["measured"] == summary["verdict_agrees"]
    rel = [abs(e.predicted_change - e.measured_change) / e.measured_change for e in verdict.baselines]
    assert np.median(rel) < 0.33
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("verdict")]
    assert len(lines) == 1 and f"from {sampled['times_read']} of 9840 times" in lines[0]


def test_eht_data_fpt_hurts_and_the_verdict_says_so(eht_imported, tmp_path, caplog):
    ref, tgt = tmp_path / "lo.ms", tmp_path / "hi.ms"
    shutil.copytree(eht_imported[0], ref)
    shutil.copytree(eht_imported[1], tgt)
    with caplog.at_level("INFO", logger="hitops"):
        report, verdict = predicted_and_measured(ref, tgt)
    summary = V.summary(verdict)
    assert summary["measured"] == 42
    assert summary["help"] <= 2 and summary["hurt"] >= 20
    assert summary["sign_agrees"] >= 0.9 * summary["measured"]
    assert summary["median_abs_error"] < 0.03
    # one summary line in the log; the table per baseline is in the report
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("verdict")]
    assert len(lines) == 1
    assert f"hurt on {summary['hurt']}," in lines[0] and "per baseline in" in lines[0]
    assert len(report["verdict"]["baselines"]) == 42
    # M87's structure at the reference band: named for the baseline methods
    closure = report["verdict"]["reference_closure"]
    assert not closure["consistent_with_zero"]
    assert "closure phases are not consistent with zero" in caplog.text
    assert "--tracker antenna" in caplog.text
    # the antenna tracker keeps the target's closures: no such warning then
    caplog.clear()
    with caplog.at_level("INFO", logger="hitops"):
        calibrate_flat(str(ref), str(tgt), method="pwc", tracker="antenna", overwrite=True)
    assert "closure phases are not consistent" not in caplog.text
    saved = json.loads(Path(str(tgt) + ".hitops-calibrate.json").read_text())
    assert saved["verdict"]["summary"]["hurt"] >= 20
