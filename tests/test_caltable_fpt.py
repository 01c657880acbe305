"""--caltable: the antenna tracker's FPT solutions as a CASA table that applycal applies.

On a noise-free point-source scene (the antenna model is exact there), CASA
applycal of the table calibrate writes must reproduce calibrate's own PWC column
on every unflagged parallel-hand sample (1e-6 rad), with and without the offset
step; with noise the two estimators (antenna solutions in the table and column
alike) are compared with the truth.  A table without the antenna tracker is
refused before anything is written.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Troposphere
from hitops.errors import InputError
from ms_columns import col  # tests/ is on sys.path (rootdir-relative)

pytestmark = pytest.mark.slow


def applycal(ms, table):
    """CASA applycal in its own process: casatools carries its own casacore, and a table
    this process still holds (dask-ms keeps handles until collected) must not see CASA
    add CORRECTED_DATA underneath it."""
    code = ("import sys; from hitops.casa.runner import run_task; "
            "run_task('applycal', vis=sys.argv[1], gaintable=[sys.argv[2]], "
            "interp=['nearest'], applymode='calflag', calwt=[False], flagbackup=False)")
    subprocess.run([sys.executable, "-c", code, str(ms), str(table)], check=True,
                   capture_output=True, timeout=300)


@pytest.mark.parametrize("offset_model", [None, "point"])
def test_applycal_of_the_table_equals_the_pwc_column(tmp_path, new_pair, offset_model):
    # a point source at the reference band (closing phases) whose stations start at
    # different wrap counts, so the offset step has integers to find
    truth = new_pair(PairSpec(n_ant=4, n_time=300, n_scans=2, seed=7,
                              corr_types=("RR", "RL", "LR", "LL"),
                              troposphere=Troposphere(phase_offset_rad=1.0, ref_offset_scale=0.0)))
    table = tmp_path / "fpt.G"
    report = calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna", caltable=str(table),
                       offset_model=offset_model, no_verdict=True)
    assert report["caltable"]["solutions"] > 0 and table.is_dir()
    pwc = col(truth.target_ms, "PWC_DATA")
    flag = col(truth.target_ms, "FLAG")
    applycal(truth.target_ms, table)
    corrected = col(truth.target_ms, "CORRECTED_DATA")
    flag_after = col(truth.target_ms, "FLAG")
    parallel = [0, 3]                      # RR, LL
    ok = ~flag[:, 0, parallel] & ~flag_after[:, 0, parallel]
    assert ok.mean() > 0.95
    diff = np.angle(corrected[:, 0, parallel].astype(np.complex128)
                    * np.conj(pwc[:, 0, parallel].astype(np.complex128)))[ok]
    assert np.max(np.abs(diff)) < 1e-6
    if offset_model:
        ks = [e["k"] for e in report["offset_step"]["antennas"]]
        assert any(ks)                     # the integers were not all zero: they were applied


def test_a_table_needs_the_antenna_tracker(tmp_path, new_pair):
    truth = new_pair(PairSpec(n_time=40, seed=3))
    with pytest.raises(InputError, match="--caltable .* needs --tracker antenna"):
        calibrate_flat(truth.ref_ms, truth.target_ms, tracker="count", caltable=str(tmp_path / "t.G"))
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert "PWC_DATA" not in t.colnames()
    assert not (tmp_path / "t.G").exists()


def test_calibrate_leaves_no_table_open_for_casa_to_invalidate(tmp_path, new_pair):
    """After calibrate returns, CASA (its own casacore) may add a column to the set and
    this process must still read it: calibrate closes the table handles dask-ms held
    (automatic garbage collection is switched off here, so only that close can help)."""
    import gc

    truth = new_pair(PairSpec(n_time=100, seed=7, corr_types=("RR", "RL", "LR", "LL"),
                              troposphere=Troposphere(ref_offset_scale=0.0)))
    table = tmp_path / "fpt.G"
    gc.disable()
    try:
        calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna", caltable=str(table),
                  no_verdict=True)
        applycal(truth.target_ms, table)
        with pt.table(str(truth.target_ms), ack=False) as t:
            assert "CORRECTED_DATA" in t.colnames()
    finally:
        gc.enable()
