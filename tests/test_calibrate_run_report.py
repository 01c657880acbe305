"""hitops/calibrate/run_report.py: one run report, written once, when everything is in it.

Before the typed report, a run wrote its JSON after the verdict, again after --caltable
and again after the conversions; a stop between them left a report without what followed.
Here a real run (antenna tracker, verdict, --caltable) on a small synthetic pair writes
the file once, and that one file holds the verdict, the caltable entry and the sections.
"""

from __future__ import annotations

import json
import pathlib

import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate.run_report import (AfterCommit, AntennaWraps, RunReport, TableTracking,
                                         write_run_report)
from hitops.testing import PairSpec


def _count_writes(monkeypatch, path: pathlib.Path):
    """How many times ``path`` is written by ``Path.write_text`` (the run's own writes go
    through it; the file is real)."""
    writes = []
    real = pathlib.Path.write_text

    def counting(self, *args, **kwargs):
        if pathlib.Path(self).resolve() == path.resolve():
            writes.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "write_text", counting)
    return writes


def test_a_run_writes_its_report_once_with_everything(new_pair, tmp_path, monkeypatch):
    truth = new_pair(PairSpec(n_ant=4, n_time=120, corr_types=("RR", "LL"), seed=3))
    path = tmp_path / "run.json"
    writes = _count_writes(monkeypatch, path)
    returned = calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna",
                         caltable=str(tmp_path / "fpt.G"), report=str(path))
    assert len(writes) == 1
    written = json.loads(path.read_text())
    assert written["caltable"]["solutions"] > 0
    assert "baselines" in written["verdict"] and "summary" in written["verdict"]
    assert written["timings_s"]["verdict"] >= 0
    assert written["tracking"]["setup"]["tracker"] == "antenna"
    # the returned report is the written one, with where it went
    assert returned.pop("report_path") == str(path)
    assert json.loads(json.dumps(returned)) == written


def test_json_of_the_typed_report(tmp_path):
    """The sections first, then what followed the commit (entries not made are left out);
    the caltable is made before the one write, and a failing step leaves no file."""
    tracking = TableTracking((AntennaWraps("PV", 0, 1, 99, 0.1), AntennaWraps("PB", 12, 0, 100, 0.2)),
                             segments=2, wrap_counting=True)
    report = RunReport(tmp_path / "r.json", {"methods": ["pwc"], "tracking": tracking.as_json()},
                       AfterCommit(verdict={"skipped": "why"}))

    def finish(after: AfterCommit):
        after.conversions = [{"from": "x.uvfits"}]

    body = write_run_report(report, lambda: {"rows": 4}, finish)
    written = json.loads((tmp_path / "r.json").read_text())
    assert list(written) == ["methods", "tracking", "verdict", "caltable", "conversions"]
    assert written["tracking"]["antennas"][1] == {
        "antenna": "PB", "wraps": 12, "flagged_solutions": 0, "solutions": 100,
        "max_residual_rad": 0.2}
    assert written["tracking"]["baselines"] == []
    assert body["report_path"] == str(tmp_path / "r.json") and "report_path" not in written

    def failing():
        raise RuntimeError("caltable failed")

    broken = RunReport(tmp_path / "broken.json", {"methods": ["pwc"]})
    with pytest.raises(RuntimeError, match="caltable failed"):
        write_run_report(broken, failing, finish)
    assert not (tmp_path / "broken.json").exists()
