"""A main table stored out of time order, read in time order without holding its sort.

dask-ms sorts such a table by TIME with one TaQL query per open and keeps the
sorted row numbers and the selection behind them for the whole run (about 37-40
bytes per row of both bands, docs/performance.md).  :func:`sort_by_time` reads
TIME once instead and keeps only which rows fall in each of a few hundred
*buckets* of consecutive distinct times, as runs of consecutive row numbers
(a baseline-major table has one run per baseline and bucket, so a few bytes per
bucket; a shuffled one keeps 4 bytes per row).  A read of positions [a, b) of the
time order (:meth:`TimeSortedRows.read`) reads the TIME of the buckets that hold
them, orders those rows by (TIME, row number), which is the order dask-ms's
``ORDERBY TIME`` gives (checked in tests/test_sorted_runs.py), and reads the asked
columns at exactly those rows with python-casacore, one getcol per run of
consecutive rows.  The caller sees the same arrays, in the same order, as a
slice of dask-ms's sorted dataset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence

import numpy as np

from ..errors import MeasurementSetError
from .match import distinct_counts
from .table_rows import MainTable, StorageRows, rows_reader

#: buckets per requested block of rows: a read of a block touches at most two buckets it
#: does not need, so it reads at most 2 / BUCKETS_PER_BLOCK more TIME values than it keeps
BUCKETS_PER_BLOCK = 8
#: keep explicit row numbers (4 bytes per row) instead of runs (16 bytes per run) when the
#: runs are shorter than this on average (shuffled tables)
MIN_MEAN_RUN = 4


@dataclass(frozen=True, eq=False)
class TimeSortedRows(StorageRows):
    """The main table of one group, read in (TIME, row number) order with python-casacore.

    Positions are those of the table sorted by time (what dask-ms's sorted dataset
    numbers 0..n_rows-1); ``bucket_time[k]`` is the first distinct-time index of
    bucket k, whose rows are positions row_start[bucket_time[k]] onwards.  A
    bucket's rows (ascending row numbers) are runs ``run_first``/``run_len`` from
    ``bucket_run[k]`` to ``bucket_run[k + 1]``, or, for a table of short runs,
    ``order[row_start[bucket_time[k]]:row_start[bucket_time[k + 1]]]``.
    """

    unique_time: np.ndarray = field(default=None)   # sorted distinct TIME values
    row_start: np.ndarray = field(default=None)     # (n_time + 1) first position of each time
    bucket_time: np.ndarray = field(default=None)   # (n_bucket + 1) first time of each bucket
    bucket_run: Optional[np.ndarray] = None         # (n_bucket + 1) first run of each bucket
    run_first: Optional[np.ndarray] = None          # first row number of each run
    run_len: Optional[np.ndarray] = None            # rows in each run
    order: Optional[np.ndarray] = None              # int32 rows by bucket (short runs only)

    def bucket_rows(self, k0: int, k1: int) -> np.ndarray:
        """Ascending row numbers of buckets [k0, k1)."""
        if self.order is not None:
            a, b = self.row_start[self.bucket_time[[k0, k1]]]
            return np.sort(self.order[a:b]).astype(np.int64)
        r0, r1 = self.bucket_run[k0], self.bucket_run[k1]
        first, length = self.run_first[r0:r1], self.run_len[r0:r1]
        by_row = np.argsort(first, kind="stable")
        first, length = first[by_row], length[by_row]
        # every run expanded: row = its run's first row + its offset in the run
        starts = np.repeat(first - np.concatenate([[0], np.cumsum(length)[:-1]]), length)
        return starts + np.arange(int(length.sum()), dtype=np.int64)

    def read(self, table: MainTable, columns: Sequence[str], rows) -> Dict[str, np.ndarray]:
        """Positions ``rows`` (a slice of the time order, or None for all) of ``columns``;
        ``ROWID`` gives the row numbers, in the same (TIME, row number) order."""
        if not (rows is None or isinstance(rows, slice)):
            raise RuntimeError(f"{self.ms}: rows of a table read in time order were asked "
                               "by position list; this is a hitops bug")
        a, b, _ = (rows or slice(None)).indices(self.n_rows)
        if b <= a:   # no row: the columns' cell shapes still, as dask-ms gives them
            return {c: v[:0] for c, v in table.read_rows(list(columns), slice(0, 1)).items()}
        t_a = int(np.searchsorted(self.row_start, a, side="right")) - 1
        t_b = int(np.searchsorted(self.row_start, b, side="left"))
        k0 = int(np.searchsorted(self.bucket_time, t_a, side="right")) - 1
        k1 = int(np.searchsorted(self.bucket_time, t_b, side="left"))
        candidates = self.bucket_rows(k0, k1)
        first, stop = self.bucket_time[k0], self.bucket_time[k1]
        base = int(self.row_start[first])
        times = rows_reader(table._table, candidates)("TIME")
        # dask-ms's ORDERBY TIME keeps the storage order of equal times: rows grouped by
        # their time, ascending within each (a counting sort over the buckets' times)
        from ..kernels.sorted_runs import bucket_rows

        edges = np.concatenate([self.unique_time[first:stop], [np.inf]])
        by_time, starts = bucket_rows(times, edges)
        in_order = times[by_time]
        if starts[0] != 0 or not np.array_equal(
                in_order, np.repeat(self.unique_time[first:stop],
                                    np.diff(self.row_start[first:stop + 1]))):
            raise MeasurementSetError(f"{self.ms}: TIME changed while it was being read; run "
                                      "again when nothing else writes to the set")
        picked = by_time[a - base:b - base]
        # read in ascending row order (runs of rows), then put the values in time order
        keep = np.zeros(candidates.size, dtype=bool)
        keep[picked] = True
        row_ids = candidates[keep]
        place = (np.cumsum(keep) - 1)[picked]
        read = rows_reader(table._table, row_ids)
        out = {}
        for column in columns:
            if column == "ROWID":
                out[column] = row_ids[place]
            elif column == "TIME":
                out[column] = in_order[a - base:b - base]
            else:
                out[column] = read(column)[place]
        return out


def sort_by_time(ms: str, block_rows: int) -> TimeSortedRows:
    """Index the main table of ``ms`` by time for reads of about ``block_rows`` positions.

    Reads TIME whole (8 bytes per row while this runs) and keeps the runs of each
    bucket of about ``block_rows / BUCKETS_PER_BLOCK`` rows (whole times per bucket).
    """
    with MainTable(ms) as table:
        n_rows = table.n_rows
        time = np.ascontiguousarray(table.read(["TIME"], 0, n_rows)["TIME"], dtype=np.float64)
    unique_time, counts = distinct_counts(time)
    row_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    target = max(1, int(block_rows) // BUCKETS_PER_BLOCK)
    # a bucket starts at the first time whose first position reaches the next multiple
    firsts = np.searchsorted(row_start[:-1], np.arange(0, n_rows, target), side="left")
    bucket_time = np.unique(np.concatenate([firsts, [unique_time.size]])).astype(np.int64)
    from ..kernels.sorted_runs import bucket_rows

    # bucket k: times [edges[k], edges[k + 1]); the last edge is past every time
    order, _ = bucket_rows(time, np.concatenate([unique_time[bucket_time[:-1]], [np.inf]]))
    del time
    starts = row_start[bucket_time]                      # first position of each bucket
    new_run = np.ones(n_rows, dtype=bool)
    new_run[1:] = np.diff(order) != 1
    new_run[starts[:-1]] = True
    run_at = np.flatnonzero(new_run)
    if run_at.size * MIN_MEAN_RUN > n_rows:              # short runs: keep the rows
        return TimeSortedRows(ms, n_rows, unique_time=unique_time, row_start=row_start,
                              bucket_time=bucket_time, order=order)
    run_len = np.diff(np.concatenate([run_at, [n_rows]]))
    return TimeSortedRows(ms, n_rows, unique_time=unique_time, row_start=row_start,
                          bucket_time=bucket_time,
                          bucket_run=np.searchsorted(run_at, starts).astype(np.int64),
                          run_first=order[run_at].astype(np.int64), run_len=run_len)
