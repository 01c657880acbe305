"""``hitops diagnose`` shows the wrap-tracking confidence numbers of ``hitops calibrate``.

A pair is calibrated with the robust trackers (one baseline with a bridged
gap and a long gap), then diagnosed: the per-baseline and per-antenna tables
must carry the numbers of the calibrate report, read from the default file
beside the MS or from --calibrate-report.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Storage, Troposphere, add_column
from hitops.diagnose import diagnose
from hitops.errors import InputError


@pytest.fixture(scope="module")
def pair(tmp_path_factory, pair_store):
    path = tmp_path_factory.mktemp("diagtrack")
    truth = pair_store.copy(PairSpec(n_ant=4, n_time=400, corr_types=("RR", "LL"), seed=9,
                                     troposphere=Troposphere(step_rad=0.1)), path)
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        t_idx = np.rint(truth.time - truth.time.min()).astype(int)
        first = (truth.ant1 == 0) & (truth.ant2 == 1)
        flag[first & (t_idx >= 100) & (t_idx < 105)] = True
        flag[first & (t_idx >= 200) & (t_idx < 280)] = True
        t.putcol("FLAG", flag)
    return truth


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_tables_carry_the_default_calibrate_report(pair, tmp_path):
    rep = calibrate_flat(pair.ref_ms, pair.target_ms, tracker="smooth", coherence_time=30.0,
                    overwrite=True)
    summary = diagnose(pair.target_ms, columns="DATA,PWC_DATA", interval=20.0,
                       intervals="5,10,20", outdir=tmp_path / "d")
    assert summary["tracking"]["tracker"] == "smooth"
    ap_sm = {e["baseline"]: e for e in rep["tracking"]["baselines"]}["AP-SM"]
    assert ap_sm["bridged_gaps"] == 2 and ap_sm["long_gap_segments"] == 2   # RR and LL
    rows = {r["baseline"]: r for r in _rows(tmp_path / "d" / "coherence-table.csv")}
    assert rows["AP-SM"]["bridged_gaps"] == "2" and rows["AP-SM"]["long_gap_segments"] == "2"
    assert rows["AP-SM"]["segments"] == "4" and rows["PV-GL"]["segments"] == "2"
    ants = {r["antenna"]: r for r in _rows(tmp_path / "d" / "antenna-table.csv")}
    # baseline mode: an antenna's numbers are the sums over its baselines
    assert ants["AP"]["bridged_gaps"] == "2" and ants["PV"]["bridged_gaps"] == "0"
    text = (tmp_path / "d" / "coherence-table.txt").read_text()
    assert "suspected slips / bridged gaps / segments / jumps" in text
    assert "0/2/4/0" in text
    json.loads((tmp_path / "d" / "summary.json").read_text())   # still valid JSON


def test_antenna_mode_numbers_and_explicit_report(pair, tmp_path):
    report = tmp_path / "ant.json"
    calibrate_flat(pair.ref_ms, pair.target_ms, tracker="antenna", coherence_time=30.0,
              overwrite=True, report=str(report), output_column="PWC_ANT")
    summary = diagnose(pair.target_ms, columns="DATA,PWC_ANT", interval=20.0,
                       intervals="5,10,20", outdir=tmp_path / "d", calibrate_report=str(report))
    assert summary["tracking"]["tracker"] == "antenna"
    assert set(summary["tracking"]["antennas"]) == {"AP", "SM", "PV", "GL"}
    ants = {r["antenna"]: r for r in _rows(tmp_path / "d" / "antenna-table.csv")}
    assert ants["AP"]["segments"] == "2"                 # RR and LL, one segment each


def test_no_report_and_bad_reports(pair, tmp_path, new_pair):
    other = new_pair(PairSpec(n_time=60, corr_types=("RR",),
                              storage=Storage(target_name="t2.ms", ref_name="r2.ms")))
    with pt.table(str(other.target_ms), ack=False) as t:
        data = t.getcol("DATA")
    add_column(other.target_ms, "CORRECTED_DATA", data * np.exp(0.1j))
    summary = diagnose(other.target_ms, columns="DATA,CORRECTED_DATA", interval=10.0,
                       intervals="5,10",
                       outdir=tmp_path / "d")
    assert summary["tracking"] is None
    rows = _rows(tmp_path / "d" / "coherence-table.csv")
    assert rows and rows[0]["segments"] == ""
    with pytest.raises(InputError, match="--calibrate-report .*no such file"):
        diagnose(other.target_ms, columns="DATA", outdir=None,
                 calibrate_report=str(tmp_path / "missing.json"))
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not a readable JSON"):
        diagnose(other.target_ms, columns="DATA", outdir=None, calibrate_report=str(bad))
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"target_ms": "x"}))
    with pytest.raises(InputError, match="no wrap-tracking section"):
        diagnose(other.target_ms, columns="DATA", outdir=None, calibrate_report=str(old))


def test_count_tracker_report_gives_empty_tracking_cells(pair, tmp_path):
    calibrate_flat(pair.ref_ms, pair.target_ms, tracker="count", overwrite=True,
              output_column="PWC_COUNT")
    summary = diagnose(pair.target_ms, columns="DATA,PWC_COUNT", interval=20.0,
                       intervals="5,10,20", outdir=tmp_path / "d")
    assert summary["tracking"]["tracker"] == "count"
    rows = _rows(tmp_path / "d" / "coherence-table.csv")
    assert rows and all(r["segments"] == "" for r in rows)
    assert all(r["segments"] == "" for r in _rows(tmp_path / "d" / "antenna-table.csv"))
