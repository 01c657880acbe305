"""The shared Measurement Set reader (hitops.io.read) against dask-ms's public API and TaQL.

Only dask-ms's public API is used.  These tests check that ``open_main``
gives the table in storage order (values, dtypes, ROWID) on a table stored
in random row order and cut into several chunks, that ``open_groups`` gives
each group's rows in time order with their ROWID, that a subset of rows
written back through ``write_main_columns`` lands on those rows only, and
that diagnose (which reads through the same code) refuses a set mixing two
fields.
"""

from __future__ import annotations

import gc
import numpy as np
import pytest

from hitops.testing import PairSpec, Signal, Storage
from hitops.errors import MeasurementSetError
from hitops.io import read as msio

COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "UVW", "DATA", "FLAG", "FLAG_ROW"]


@pytest.fixture(scope="module")
def pair(pair_store):
    """The session's build, shared: the tests below read it, or write into copies of it."""
    return pair_store.built(PairSpec(n_ant=4, n_time=50, seed=3,
                                     signal=Signal(sigma_ref=0.1, sigma_target=0.1),
                                     storage=Storage(shuffle_target=True)))


def test_open_main_matches_xds_from_ms(pair):
    import dask
    from daskms import xds_from_ms

    ms = str(pair.target_ms)
    ours = msio.open_main(ms, COLUMNS, chunk_rows=77)       # several uneven chunks
    (theirs,) = xds_from_ms(ms, columns=COLUMNS, index_cols=[], group_cols=[],
                            chunks={"row": 77})
    assert ours.chunks["row"] == theirs.chunks["row"]
    got, want = dask.compute({c: ours[c].data for c in COLUMNS + ["ROWID"]},
                             {c: theirs[c].data for c in COLUMNS + ["ROWID"]},
                             scheduler="sync")
    for c in COLUMNS + ["ROWID"]:
        assert got[c].dtype == want[c].dtype, c
        np.testing.assert_array_equal(got[c], want[c], err_msg=c)
    # storage order, checked against python-casacore directly
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t:
        np.testing.assert_array_equal(got["TIME"], t.getcol("TIME"))
        np.testing.assert_array_equal(got["DATA"], t.getcol("DATA"))
    np.testing.assert_array_equal(got["ROWID"], np.arange(got["TIME"].size))


def test_open_groups_gives_time_order_with_row_numbers(pair):
    """A shuffled table read through open_groups: TIME ascending, ROWID the table's rows."""
    import dask
    from casacore import tables as pt

    ms = str(pair.target_ms)
    (key, ds), = msio.open_groups(ms, ["TIME", "DATA"], chunks=(100, 150, 50)).items()
    assert key == (0, 0)
    with pt.table(ms, ack=False) as t:
        time, data = t.getcol("TIME"), t.getcol("DATA")
    assert ds.chunks["row"] == (100, 150, 50) and time.size == 300
    rowid, got_time, got_data = dask.compute(ds.ROWID.data, ds.TIME.data, ds.DATA.data,
                                             scheduler="sync")
    assert np.all(np.diff(got_time) >= 0)
    assert not np.all(np.diff(rowid) > 0)             # the storage order was not time order
    np.testing.assert_array_equal(np.sort(rowid), np.arange(time.size))
    np.testing.assert_array_equal(got_time, time[rowid])
    np.testing.assert_array_equal(got_data, data[rowid])


def test_time_ordered_tables_are_read_in_storage_order(pair, tmp_path):
    """is_time_ordered sees the shuffled table and a time-sorted copy (also across its
    read blocks); the sorted copy opens without dask-ms's sort, in storage order."""
    import dask
    from casacore import tables as pt

    ms = str(pair.target_ms)
    assert not msio.is_time_ordered(ms)
    sorted_ms = str(tmp_path / "sorted.ms")
    with pt.table(ms, ack=False) as t:
        t.sort("TIME").copy(sorted_ms, deep=True).close()
    assert msio.is_time_ordered(sorted_ms) and msio.is_time_ordered(sorted_ms, block_rows=7)
    with pt.table(sorted_ms, readonly=False, ack=False) as t:   # one step back at row 200
        times = t.getcol("TIME")
        times[200] = times[199] - 1.0
        t.putcol("TIME", times)
    assert not msio.is_time_ordered(sorted_ms, block_rows=200)
    times[200] = times[199]
    with pt.table(sorted_ms, readonly=False, ack=False) as t:
        t.putcol("TIME", times)
    (key, ds), = msio.open_groups(sorted_ms, ["TIME"], chunks=(100, 200)).items()
    rowid, got = dask.compute(ds.ROWID.data, ds.TIME.data, scheduler="sync")
    np.testing.assert_array_equal(rowid, np.arange(300))
    np.testing.assert_array_equal(got, times)


def test_read_rows_subset_and_write_back(pair, tmp_path):
    import shutil

    ms = str(tmp_path / "copy.ms")
    shutil.copytree(pair.target_ms, ms)
    n_row = msio.read_main_columns(ms, ["TIME"])["TIME"].size
    rows = np.r_[3:40, 55:60, n_row - 7:n_row]
    part = msio.read_main_columns(ms, ["DATA", "TIME"], rows=rows, chunk_rows=64)
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t:
        np.testing.assert_array_equal(part["DATA"], t.getcol("DATA")[rows])
    new = (part["DATA"] * 2j).astype(np.complex64)
    msio.write_main_columns(ms, rows, {"OUT_DATA": new}, {"OUT_DATA": ("row", "chan", "corr")})
    with pt.table(ms, ack=False) as t:
        out = t.getcol("OUT_DATA")
        data = t.getcol("DATA")
    np.testing.assert_array_equal(out[rows], new)
    untouched = np.setdiff1d(np.arange(n_row), rows)
    assert not np.any(out[untouched] == data[untouched] * 2j)


def test_selection_columns_and_diagnose_refuses_two_fields(pair, tmp_path):
    import shutil

    from casacore import tables as pt

    from hitops.diagnose.read import read_grid

    ms = str(tmp_path / "two-fields.ms")
    shutil.copytree(pair.target_ms, ms)
    assert msio.selection_columns(ms) == []
    with pt.table(f"{ms}::FIELD", readonly=False, ack=False) as t:
        t.addrows(1)
    with pt.table(ms, readonly=False, ack=False) as t:
        field = t.getcol("FIELD_ID")
        field[::2] = 1
        t.putcol("FIELD_ID", field)
    assert msio.selection_columns(ms) == ["DATA_DESC_ID", "FIELD_ID"]
    with pytest.raises(MeasurementSetError, match="several fields.*FIELD_ID=1"):
        read_grid(ms, ["DATA"])


def test_slices_and_row_subsets_are_read(pair, monkeypatch):
    """compute_columns reads a slice or a row subset exactly; MainTable reads a row range of
    exactly the columns asked for; the tests' read counter (tests/read_spy.py) sees them all."""
    from casacore import tables as pt

    from read_spy import record_reads

    ms = str(pair.target_ms)
    with pt.table(ms, ack=False) as t:
        time, ant1 = t.getcol("TIME"), t.getcol("ANTENNA1")
    rows = np.array([3, 4, 5, 90, 91, 150])
    with record_reads(monkeypatch) as reads:
        ds = msio.open_main(ms, ["TIME", "ANTENNA1"], chunk_rows=60)
        block, subset, whole = msio.compute_columns(
            [(ds, ["TIME"], slice(60, 120)), (ds, ["TIME", "ANTENNA1"], rows),
             (ds, ["ANTENNA1"], None)])
        with msio.MainTable(ms) as table:
            assert table.n_rows == time.size
            direct = table.read(["ANTENNA1", "TIME"], 30, 95)
    assert np.array_equal(block["TIME"], time[60:120])
    assert np.array_equal(subset["TIME"], time[rows])
    assert np.array_equal(subset["ANTENNA1"], ant1[rows])
    assert np.array_equal(whole["ANTENNA1"], ant1)
    assert sorted(direct) == ["ANTENNA1", "TIME"]
    assert np.array_equal(direct["TIME"], time[30:95])
    assert np.array_equal(direct["ANTENNA1"], ant1[30:95])
    assert reads == [(ms, ("TIME",), 60), (ms, ("TIME", "ANTENNA1"), rows.size),
                     (ms, ("ANTENNA1",), time.size), (ms, ("ANTENNA1", "TIME"), 65)]

def test_open_for_reading_direct_only_for_one_valid_group(new_pair):
    """A set of one field and one spectral window read in one chunk is read by
    python-casacore (StorageRows); rows naming a FIELD row the set lacks go through the
    grouped datasets, whose keys let the plan name the damage (as before)."""
    from casacore import tables as pt

    truth = new_pair(PairSpec(n_ant=3, n_time=40))
    ms = str(truth.target_ms)
    opened = msio.open_for_reading(ms, ["TIME", "DATA"], 1000, time_ordered=True, direct=True)
    assert list(opened) == [(0, 0)] and isinstance(opened[(0, 0)], msio.StorageRows)
    assert opened[(0, 0)].n_rows == truth.time.size
    got, = msio.compute_columns([(opened[(0, 0)], ["DATA", "ROWID"], np.array([2, 3, 9]))])
    with pt.table(ms, ack=False) as t:
        assert np.array_equal(got["DATA"], t.getcol("DATA")[[2, 3, 9]])
    assert np.array_equal(got["ROWID"], [2, 3, 9])
    # not direct (a cluster, several chunks): dask-ms's datasets
    grouped = msio.open_for_reading(ms, ["TIME"], 1000, time_ordered=True, direct=False)
    assert not isinstance(grouped[(0, 0)], msio.StorageRows)
    del grouped
    gc.collect()   # dask-ms closes its table handle when the dataset is collected
    with pt.table(ms, readonly=False, ack=False) as t:
        field = t.getcol("FIELD_ID")
        field[5] = 3
        t.putcol("FIELD_ID", field)
    damaged = msio.open_for_reading(ms, ["TIME"], 1000, time_ordered=True, direct=True)
    assert sorted(damaged) == [(0, 0), (3, 0)]
