"""Bad input to hitops calibrate: a clear message naming the thing and the remedy,
a non-zero exit, and both Measurement Sets unchanged (every file but the lock)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Storage, add_column
from hitops.errors import (ColumnError, InputError, MeasurementSetError, OutputExistsError,
                           StationError)


def snapshot(*paths):
    digests = {}
    for root in paths:
        for dirpath, _, files in os.walk(root):
            for name in files:
                if name == "table.lock":
                    continue
                path = Path(dirpath) / name
                digests[str(path)] = hashlib.sha1(path.read_bytes()).hexdigest()
    return digests


@pytest.fixture(scope="module")
def pair(pair_store):
    """The session's build, shared: every check below asserts that it is left unchanged."""
    return pair_store.built(PairSpec(n_time=50, seed=21))


def check(pair, error, match, **kwargs):
    ref = kwargs.pop("ref_ms", pair.ref_ms)
    tgt = kwargs.pop("target_ms", pair.target_ms)
    before = snapshot(pair.ref_ms, pair.target_ms)
    with pytest.raises(error, match=match):
        calibrate_flat(ref, tgt, **kwargs)
    assert snapshot(pair.ref_ms, pair.target_ms) == before
    assert not Path(str(pair.target_ms) + ".hitops-calibrate.json").exists()


def test_missing_measurement_set(pair, tmp_path):
    check(pair, MeasurementSetError, r"reference-band .*nope\.ms' does not exist",
          ref_ms=tmp_path / "nope.ms")
    check(pair, MeasurementSetError, r"target-band .*nope\.ms' does not exist",
          target_ms=tmp_path / "nope.ms")


def test_missing_columns(pair):
    check(pair, ColumnError, r"has no column CORRECTED_DATA; check --ref-column",
          ref_column="CORRECTED_DATA")
    check(pair, ColumnError, r"has no column MODEL_DATA.*--ref-model-column",
          ref_model_column="MODEL_DATA")
    check(pair, ColumnError, r"target-band .* has no column FFSC; check .*--offset-reference-column",
          offset_reference_column="FFSC")


def test_bad_ratio_and_options(pair):
    check(pair, InputError, r"--ratio -1.0: R = nu_target / nu_reference must be a positive", ratio=-1.0)
    check(pair, InputError, r"--ratio 0.0", ratio=0.0)
    check(pair, InputError, r"unknown method 'fpt'; choose from pwc, cfpt, cwu", method="pwc,fpt")
    check(pair, InputError, r"--output-column X names one column but --method lists 2",
          method="pwc,cfpt", output_column="X")
    check(pair, InputError, r"output column DATA .* is an input or flag column", output_column="DATA")
    check(pair, InputError, r"--antenna-map entry 'JC' is not REF=TARGET", antenna_map="JC")
    check(pair, StationError, r"reference station JC is not in", antenna_map="JC=SM")
    check(pair, InputError, r"same set", target_ms=pair.ref_ms)
    check(pair, InputError, r"--time-tolerance 0.0 must be a positive", time_tolerance=0.0)
    check(pair, InputError, r"--max-offset-wraps -1 must be >= 0", max_offset_wraps=-1)
    check(pair, InputError, r"--tracker: unknown value 'nope'", tracker="nope")


def test_existing_output_column_needs_overwrite(new_pair):
    truth = new_pair(PairSpec(n_time=40, seed=22))
    add_column(truth.target_ms, "PWC_DATA", np.ones((truth.time.size, 2)))
    check(truth, OutputExistsError, r"column PWC_DATA already exists in .*target\.ms; pass --overwrite")
    calibrate_flat(truth.ref_ms, truth.target_ms, overwrite=True)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert not np.allclose(t.getcol("PWC_DATA"), 1)


def test_no_station_in_common(new_pair):
    truth = new_pair(PairSpec(n_time=40, seed=23, ref_names=("AP", "JC", "PV", "GL"),
                              target_names=("AA", "SM", "LM", "AZ")))
    check(truth, StationError,
          r"no baseline of .*target\.ms has both stations in .*ref\.ms .*--antenna-map REF=TARGET")


def test_stations_with_one_code_far_apart(new_pair):
    """Two stations that share a code but whose positions disagree are not paired."""
    truth = new_pair(PairSpec(n_time=40, seed=23))
    with pt.table(f"{truth.ref_ms}::ANTENNA", readonly=False, ack=False) as t:
        pos = t.getcol("POSITION")
        pos[1] += [3000.0, 4000.0, 0.0]    # 5 km away
        t.putcol("POSITION", pos)
    check(truth, StationError, r"station SM of .*ref\.ms and station SM of .*target\.ms share "
          r"a code but are 5\.0 km apart .*--antenna-map")


def test_placeholder_names_without_station_codes(new_pair):
    truth = new_pair(PairSpec(n_time=40, seed=23))
    with pt.table(f"{truth.target_ms}::ANTENNA", readonly=False, ack=False) as t:
        t.putcol("NAME", ["1", "2", "3", "4"])
        t.putcol("STATION", ["AP", "", "PV", "GL"])
    check(truth, StationError, r"target-band .*antenna\(s\) 1 have no usable station name")


def test_no_overlapping_times(new_pair):
    truth = new_pair(PairSpec(n_time=40, seed=24, storage=Storage(ref_time_shift=3600.0)))
    check(truth, MeasurementSetError, r"no row of .*target\.ms has a counterpart in .*ref\.ms at "
          r"the same time \(tolerance 0.5 s\)")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_time(new_pair, bad):
    truth = new_pair(PairSpec(n_time=40, seed=25))
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        time = t.getcol("TIME")
        time[17] = bad
        t.putcol("TIME", time)
    check(truth, MeasurementSetError, r"ref\.ms: TIME of row 17 is (nan|inf); rows without a "
          r"valid time cannot be matched")


def _add_subtable_row(ms, subtable):
    with pt.table(f"{ms}::{subtable}", readonly=False, ack=False) as t:
        t.addrows(1)
        for c in t.colnames():
            try:
                t.putcell(c, 1, t.getcell(c, 0))
            except Exception:
                pass


def test_fields_that_cannot_be_told_apart(new_pair):
    """Several groups are calibrated one by one (tests/test_calibrate_groups.py); two fields of
    one name are refused, since fields are paired between the bands by name."""
    truth = new_pair(PairSpec(n_time=40, seed=25))
    _add_subtable_row(truth.ref_ms, "FIELD")
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        field = t.getcol("FIELD_ID")
        field[::3] = 1
        t.putcol("FIELD_ID", field)
    _add_subtable_row(truth.target_ms, "DATA_DESCRIPTION")
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        dd = t.getcol("DATA_DESC_ID")
        dd[::2] = 1
        t.putcol("DATA_DESC_ID", dd)
    check(truth, MeasurementSetError, r"ref.ms: 2 fields named 'SYNTH' \(FIELD_ID 0, 1\) hold "
          r"data;.*rename them")


def test_channel_counts_that_disagree_are_refused(new_pair):
    # several channels are calibrated one ratio each (issue 26), but the window's tables must
    # agree: NUM_CHAN against CHAN_FREQ, then the DATA column against NUM_CHAN
    truth = new_pair(PairSpec(n_time=40, seed=26))
    with pt.table(f"{truth.ref_ms}::SPECTRAL_WINDOW", readonly=False, ack=False) as t:
        t.putcol("NUM_CHAN", np.array([4], np.int32))
    check(truth, MeasurementSetError, r"reference-band .* spectral window 0 has NUM_CHAN 4 "
          r"but 1 CHAN_FREQ values")
    with pt.table(f"{truth.ref_ms}::SPECTRAL_WINDOW", readonly=False, ack=False) as t:
        t.putcell("CHAN_FREQ", 0, t.getcell("CHAN_FREQ", 0)[0] + np.arange(4) * 1e6)
    check(truth, MeasurementSetError, r"reference-band .* column DATA has 1 channel\(s\) but "
          r"spectral window 0 has 4")


@pytest.mark.slow
def test_cli_exit_status_and_message(pair, tmp_path):
    before = snapshot(pair.ref_ms, pair.target_ms)
    hitops = Path(sys.executable).with_name("hitops")
    proc = subprocess.run([str(hitops), "calibrate", str(pair.ref_ms), str(pair.target_ms),
                           "--ratio", "-2"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "--ratio -2.0: R = nu_target / nu_reference must be a positive" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert snapshot(pair.ref_ms, pair.target_ms) == before


@pytest.mark.parametrize("band", ["target", "reference"])
@pytest.mark.parametrize("chunk_rows", [0, 300])
def test_two_rows_in_one_cell_are_refused_whole_or_chunked(new_pair, chunk_rows, band):
    """Two rows of one baseline at one time, in either band, are refused before anything
    is written, whether the run reads the set whole or checks it chunk by chunk from
    the index pass's pair keys (hitops/calibrate/band_index.py, hitops/kernels/cells.py)."""
    truth = new_pair(PairSpec(n_time=400, seed=2))
    late = 250   # a row of the first baseline (stored baseline by baseline), late in the track
    changed = truth.target_ms if band == "target" else truth.ref_ms
    with pt.table(str(changed), readonly=False, ack=False) as t:
        t.putcell("TIME", late, t.getcell("TIME", late - 1))
    with pt.table(str(truth.target_ms), ack=False) as t:
        names = set(t.colnames())
    with pytest.raises(MeasurementSetError,
                       match=rf"{changed}: 1 rows share a \(baseline, time\) cell"):
        calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", chunk_rows=chunk_rows)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert set(t.colnames()) == names
