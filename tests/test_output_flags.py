"""New flags are staged only for chunks where they change FLAG (hitops/calibrate/output.py).

A chunk whose new flags equal FLAG stages none; the commit then leaves its rows as
they are.  The result must not depend on it: flags changed in one chunk of several
give the same FLAG, backup and report as the run in one chunk, in time order and
baseline by baseline, and a rerun with --overwrite (whose input flags are the
backup) gives the same again.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.calibrate.output import FLAG_BACKUP
from hitops.testing import PairSpec, Storage

from ms_columns import col  # tests/ is on sys.path (rootdir-relative)


@pytest.mark.parametrize("time_order", [True, False])
def test_flags_changed_in_one_chunk_only(new_pair, tmp_path, time_order):
    truth = new_pair(PairSpec(n_ant=5, n_time=3000, seed=12,
                              storage=Storage(time_order=time_order)))
    # the reference is flagged for one baseline over a tenth of the track: only the chunk
    # holding those times changes FLAG
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        a1, a2, tm = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("TIME")
        flag = t.getcol("FLAG")
        hit = (a1 == 0) & (a2 == 1) & (tm > np.quantile(tm, 0.4)) & (tm < np.quantile(tm, 0.5))
        flag[hit] = True
        t.putcol("FLAG", flag)
    other = tmp_path / "chunked.ms"
    shutil.copytree(truth.target_ms, other)
    whole = calibrate_flat(truth.ref_ms, truth.target_ms)
    chunked = calibrate_flat(truth.ref_ms, str(other), chunk_rows=3000)
    assert whole["chunks"] == 1 and chunked["chunks"] > 4
    want = (truth.ant1 == 0) & (truth.ant2 == 1) & (truth.time > np.quantile(truth.time, 0.4)) \
        & (truth.time < np.quantile(truth.time, 0.5))
    for ms, report in ((truth.target_ms, whole), (str(other), chunked)):
        assert np.array_equal(col(ms, "FLAG").any(axis=(1, 2)), want)
        assert report["flags"]["flag_updated"] and report["flags"]["backup_created"]
        assert not col(ms, FLAG_BACKUP).any()
    for column in ("FLAG", "PWC_DATA"):
        np.testing.assert_array_equal(col(str(other), column), col(truth.target_ms, column))
    # a rerun: the new flags equal FLAG everywhere, nothing is staged, nothing changes
    again = calibrate_flat(truth.ref_ms, str(other), chunk_rows=3000, overwrite=True)
    assert not again["flags"]["flag_updated"] and not again["flags"]["backup_created"]
    for column in ("FLAG", "PWC_DATA", FLAG_BACKUP):
        np.testing.assert_array_equal(col(str(other), column), col(truth.target_ms, column))
    with pt.table(str(other), ack=False) as t:
        assert not [c for c in t.colnames() if c.startswith("HITOPS_PARTIAL_")]
