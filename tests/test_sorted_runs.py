"""Distinct values and lookups of run-sorted columns (hitops/kernels/sorted_runs.py)."""

import numpy as np
import pytest

from hitops.io.match import distinct_counts
from hitops.kernels.sorted_runs import count_runs, lookup_sorted, run_distinct_counts

RNG = np.random.default_rng(7)
TIMES = 5.0e9 + np.arange(500) * 1.0


def layouts():
    per_baseline = [TIMES[RNG.random(TIMES.size) < 0.8] for _ in range(6)]   # gaps differ
    return {
        "time-ordered": np.repeat(TIMES, 6),
        "baseline-major": np.tile(TIMES, 6),
        "baseline-major with gaps": np.concatenate(per_baseline),
        "shuffled": RNG.permutation(np.repeat(TIMES, 6)),
        "one row": TIMES[:1],
        "descending": TIMES[::-1].copy(),
    }


@pytest.mark.parametrize("name", list(layouts()))
def test_distinct_counts_equal_numpy(name):
    values = layouts()[name]
    distinct, counts = distinct_counts(values)
    want, want_counts = np.unique(values, return_counts=True)
    assert np.array_equal(distinct, want)
    assert np.array_equal(counts, want_counts)
    assert counts.dtype == np.int64


def test_distinct_counts_empty():
    distinct, counts = distinct_counts(np.zeros(0))
    assert distinct.size == 0 and counts.size == 0


def test_run_kernel_parts():
    values = np.array([1.0, 2.0, 2.0, 4.0, 0.5, 2.0, 3.0, 4.0, 1.0, 4.0])
    assert count_runs(values) == 3
    distinct, counts, extra = run_distinct_counts(values)
    assert distinct.tolist() == [1.0, 2.0, 4.0]
    assert counts.tolist() == [2, 3, 3]
    assert sorted(extra.tolist()) == [0.5, 3.0]
    assert values.tolist() == [1.0, 2.0, 2.0, 4.0, 0.5, 2.0, 3.0, 4.0, 1.0, 4.0]   # untouched


@pytest.mark.parametrize("name", list(layouts()))
def test_lookup_sorted_equals_searchsorted(name):
    values = layouts()[name]
    table = np.unique(values)
    at = lookup_sorted(values, table)
    assert np.array_equal(at, np.searchsorted(table, values))
    assert np.array_equal(table[at], values)


def test_lookup_sorted_marks_absent_values():
    table = np.array([1.0, 3.0, 5.0, 7.0])
    values = np.array([0.0, 1.0, 2.0, 7.0, 8.0, 3.0, 6.0, 5.0])
    assert lookup_sorted(values, table).tolist() == [-1, 0, -1, 3, -1, 1, -1, 2]
    assert lookup_sorted(values, np.zeros(0)).tolist() == [-1] * 8


# ---- hitops/io/time_sorted.py: a table stored out of time order, read in time order

from hitops.io import read as msio
from hitops.io.time_sorted import TimeSortedRows, sort_by_time
from hitops.testing import PairSpec, Storage

READ = ["ROWID", "TIME", "ANTENNA1", "ANTENNA2", "DATA", "FLAG"]
STORAGES = {"baseline-major": Storage(),
            "shuffled": Storage(shuffle_target=True),
            "time order": Storage(time_order=True)}


def _dask_ms_sorted(ms):
    """dask-ms's own sort of the table by TIME (what calibrate used before)."""
    from daskms import xds_from_ms

    (ds,) = xds_from_ms(ms, columns=READ[1:], index_cols=["TIME"], group_cols=[],
                        chunks={"row": 10 ** 6})
    return {c: ds[c].values for c in READ}


@pytest.mark.parametrize("layout", list(STORAGES))
def test_time_sorted_rows_read_what_dask_ms_sorts(shared_pair, layout):
    """Any slice of the time order, across bucket edges and inside a time, gives the
    rows, values and order of dask-ms's ORDERBY TIME (equal times in storage order)."""
    truth = shared_pair(PairSpec(n_ant=5, n_time=300, seed=4, n_scans=2,
                                 storage=STORAGES[layout]))
    ms = str(truth.target_ms)
    want = _dask_ms_sorted(ms)
    n = want["TIME"].size
    reader = sort_by_time(ms, block_rows=800)      # buckets of ~100 rows: 30 of them
    assert reader.bucket_start.size > 20
    assert isinstance(reader, TimeSortedRows) and reader.n_rows == n
    assert (reader.order is not None) == (layout == "shuffled")   # short runs: row numbers
    for rows in (slice(0, n), slice(0, 7), slice(7, 161), slice(333, 334), slice(n - 9, n),
                 slice(15, 15), None):
        got = msio.compute_columns([(reader, READ, rows)])[0]
        sel = rows or slice(None)
        for c in READ:
            assert got[c].dtype == want[c].dtype, c
            np.testing.assert_array_equal(got[c], want[c][sel], err_msg=f"{c} {rows}")
    # a wrong implementation that keeps the candidates' storage order fails here
    assert not np.array_equal(want["ROWID"], np.sort(want["ROWID"])) or layout == "time order"


def test_open_for_reading_chooses_the_reader(shared_pair):
    """local runs of one-group sets: python-casacore in either order; a cluster run: dask-ms."""
    bm = str(shared_pair(PairSpec(n_ant=4, n_time=60, seed=5)).target_ms)
    to = str(shared_pair(PairSpec(n_ant=4, n_time=60, seed=5,
                                  storage=Storage(time_order=True))).target_ms)
    assert isinstance(msio.open_for_reading(bm, READ[1:], 100, False, False, local=True)[(0, 0)],
                      TimeSortedRows)
    got = msio.open_for_reading(to, READ[1:], 100, True, False, local=True)[(0, 0)]
    assert type(got) is msio.StorageRows
    for ms, ordered in ((bm, False), (to, True)):
        ds = msio.open_for_reading(ms, READ[1:], 100, ordered, False, local=False)[(0, 0)]
        assert not isinstance(ds, msio.StorageRows)


def test_a_table_changed_after_indexing_is_refused(new_pair):
    from casacore import tables as pt

    from hitops.errors import MeasurementSetError

    truth = new_pair(PairSpec(n_ant=4, n_time=60, seed=6))
    ms = str(truth.target_ms)
    reader = sort_by_time(ms, block_rows=80)
    with pt.table(ms, readonly=False, ack=False) as t:
        t.putcell("TIME", 3, t.getcell("TIME", 3) + 0.25)
    with pytest.raises(MeasurementSetError, match="TIME changed while it was being read"):
        msio.compute_columns([(reader, READ, slice(0, reader.n_rows))])


def test_a_local_run_keeps_no_dask_ms_order_in_its_budget():
    """Without dask-ms (no cluster, one group) only the pair keys and the rows written stay
    per row, so a 10^7-row baseline-major pair is cut into chunks of more than 100 000 rows
    (the floor dask-ms's sort left it at) within the 1 GB default."""
    from hitops.calibrate.memory import (FIXED_BYTES, LOCAL_ORDER_BYTES_PER_ROW, bytes_per_row,
                                         read_bytes_per_row, rows_for_budget)

    n = 2 * 10 ** 7
    sorted_by_dask_ms = rows_for_budget(10 ** 9, n, 4, 1, 1, time_ordered=False, strict=False)
    local = rows_for_budget(10 ** 9, n, 4, 1, 1, time_ordered=False, strict=False, local=True)
    assert sorted_by_dask_ms == 100_000 < local
    room = 10 ** 9 - FIXED_BYTES - LOCAL_ORDER_BYTES_PER_ROW * n
    assert local == room // (bytes_per_row(4, 1, 1) + read_bytes_per_row(4, 1))
    assert local == rows_for_budget(10 ** 9, n, 4, 1, 1, time_ordered=True, strict=False,
                                    local=True)


@pytest.mark.parametrize("layout", ["baseline-major", "shuffled"])
def test_a_time_sorted_band_indexed_in_storage_order_equals_its_sorted_rows(shared_pair,
                                                                            layout):
    """index_bands reads a TimeSortedRows band in storage order (contiguous blocks) and
    places each row's pair key in the time order: keys, distinct times, their counts and
    each time's scan (its last row's, in dask-ms's ORDERBY TIME) must equal those of the
    sorted table; a wrong placement (keys left in storage order) fails."""
    from hitops.calibrate.band_index import INDEX_COLUMNS, BandSource, index_bands

    truth = shared_pair(PairSpec(n_ant=5, n_time=300, seed=4, n_scans=2,
                                 storage=STORAGES[layout]))
    ms = str(truth.target_ms)
    want = _dask_ms_sorted(ms)
    from daskms import xds_from_ms

    (ds,) = xds_from_ms(ms, columns=["SCAN_NUMBER"], index_cols=["TIME"], group_cols=[])
    scans = ds.SCAN_NUMBER.values
    n = want["TIME"].size
    reader = sort_by_time(ms, block_rows=700)
    source = BandSource(ms=ms, ds=reader, n_row=n, n_ant=5)
    band, = index_bands([source], [INDEX_COLUMNS], block_rows=700)
    key = want["ANTENNA1"].astype(np.int64) * 5 + want["ANTENNA2"]
    assert band.pair_key is not None and np.array_equal(band.pair_key, key)
    times, counts = np.unique(want["TIME"], return_counts=True)
    assert np.array_equal(band.unique_time, times) and np.array_equal(band.time_rows, counts)
    last = np.flatnonzero(np.concatenate([want["TIME"][1:] != want["TIME"][:-1], [True]]))
    assert np.array_equal(band.time_scan, scans[last])
    with pt_table(ms) as t:
        stored_key = t.getcol("ANTENNA1").astype(np.int64) * 5 + t.getcol("ANTENNA2")
    assert not np.array_equal(band.pair_key, stored_key)


def pt_table(ms):
    from casacore import tables as pt

    return pt.table(ms, ack=False)
