"""A main table stored out of time order, read in time order without holding its sort.

dask-ms sorts such a table by TIME with one TaQL query per open and keeps the
sorted row numbers and the selection behind them for the whole run (about 37-40
bytes per row of both bands, docs/performance.md).  :func:`sort_by_time` reads
TIME in blocks instead (never more rows at once than a chunk) and keeps only which
rows fall in each *bucket*, a range of TIME holding about an eighth of a read
block, as runs of consecutive row numbers (a baseline-major table has one run per
baseline and bucket, so a few bytes per bucket; a shuffled one keeps 4 bytes per
row).  A read of positions [a, b) of the
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

from ..errors import TimeChangedError
from .table_rows import MainTable, StorageRows, rows_reader

#: buckets per requested block of rows: a read of a block touches at most two buckets it
#: does not need, so it reads at most 2 / BUCKETS_PER_BLOCK more TIME values than it keeps
BUCKETS_PER_BLOCK = 8
#: equal-width time bins counted to place the buckets' edges (1 M bins: a 12-h track in
#: bins of 0.04 s, finer than any integration)
TIME_BINS = 1 << 20
#: keep explicit row numbers (4 bytes per row) instead of runs (12 bytes per run) when the
#: runs are shorter than this on average (shuffled tables)
MIN_MEAN_RUN = 4


@dataclass(frozen=True, eq=False)
class TimeSortedRows(StorageRows):
    """The main table of one group, read in (TIME, row number) order with python-casacore.

    Positions are those of the table sorted by time (what dask-ms's sorted dataset
    numbers 0..n_rows-1).  Bucket k holds the rows with edges[k] <= TIME <
    edges[k + 1], at positions bucket_start[k] onwards; its rows (ascending row
    numbers) are runs ``run_first``/``run_len`` from ``bucket_run[k]`` to
    ``bucket_run[k + 1]``, or, for a table of short runs,
    ``order[bucket_start[k]:bucket_start[k + 1]]``.
    """

    edges: np.ndarray = field(default=None)          # (n_bucket + 1) TIME edges, -inf..inf
    bucket_start: np.ndarray = field(default=None)   # (n_bucket + 1) first position
    bucket_run: Optional[np.ndarray] = None          # (n_bucket + 1) first run of each bucket
    run_first: Optional[np.ndarray] = None           # first row number of each run
    run_len: Optional[np.ndarray] = None             # rows in each run
    order: Optional[np.ndarray] = None               # int32 rows by bucket (short runs only)

    def bucket_rows(self, k0: int, k1: int) -> np.ndarray:
        """Ascending row numbers of buckets [k0, k1)."""
        if self.order is not None:
            return np.sort(self.order[self.bucket_start[k0]:self.bucket_start[k1]]).astype(np.int64)
        r0, r1 = self.bucket_run[k0], self.bucket_run[k1]
        first, length = self.run_first[r0:r1], self.run_len[r0:r1].astype(np.int64)
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
        k0 = int(np.searchsorted(self.bucket_start, a, side="right")) - 1
        k1 = int(np.searchsorted(self.bucket_start, b, side="left"))
        candidates = self.bucket_rows(k0, k1)
        base = int(self.bucket_start[k0])
        times = rows_reader(table._table, candidates)("TIME")
        # dask-ms's ORDERBY TIME keeps the storage order of equal times: a stable sort of
        # rows in ascending row order (a baseline-major bucket is one sorted run per baseline)
        by_time = np.argsort(times, kind="stable")
        in_order = times[by_time]
        # each bucket still holds the rows it was indexed with (else TIME was rewritten)
        at_edges = np.searchsorted(in_order, self.edges[k0:k1 + 1], side="left")
        if not np.array_equal(at_edges, self.bucket_start[k0:k1 + 1] - base):
            raise TimeChangedError(self.ms)
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


def sort_by_time(ms: str, block_rows: int) -> Optional[TimeSortedRows]:
    """Index the main table of ``ms`` by time for reads of about ``block_rows`` positions.

    TIME is read three times in blocks of ``block_rows`` rows (never more at once):
    its range, a histogram of it, then each row's bucket, kept as runs of rows (the
    buckets have about ``block_rows / BUCKETS_PER_BLOCK`` rows each, and whole times).
    None when TIME holds a value that is not finite (the index pass names the row).
    """
    block_rows = max(1, int(block_rows))
    with MainTable(ms) as table:
        n_rows = table.n_rows

        def blocks():
            for start in range(0, n_rows, block_rows):
                stop = min(n_rows, start + block_rows)
                yield start, np.asarray(table.read(["TIME"], start, stop)["TIME"], np.float64)

        lo, hi = np.inf, -np.inf
        for _, time in blocks():
            if not np.all(np.isfinite(time)):
                return None
            lo, hi = min(lo, float(time.min())), max(hi, float(time.max()))
        edges = _bucket_edges(blocks(), lo, hi, n_rows, block_rows)
        runs, counts = _runs(blocks(), edges)
    bucket_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    first, length, bucket = runs
    by_bucket = np.lexsort((first, bucket))
    first, length, bucket = first[by_bucket], length[by_bucket], bucket[by_bucket]
    common = dict(edges=edges, bucket_start=bucket_start)
    if first.size * MIN_MEAN_RUN > n_rows:               # short runs: keep the rows
        starts = np.repeat(first - np.concatenate([[0], np.cumsum(length)[:-1]]), length)
        order = (starts + np.arange(n_rows)).astype(np.int32)
        return TimeSortedRows(ms, n_rows, order=order, **common)
    return TimeSortedRows(ms, n_rows, bucket_run=np.searchsorted(
        bucket, np.arange(edges.size)).astype(np.int64), run_first=first,
        run_len=length.astype(np.int32), **common)


def _bucket_edges(blocks, lo: float, hi: float, n_rows: int, block_rows: int) -> np.ndarray:
    """TIME edges of buckets of about block_rows / BUCKETS_PER_BLOCK rows, from a
    histogram of TIME in TIME_BINS equal bins over [lo, hi]; -inf and inf at the ends."""
    n_bins = int(min(TIME_BINS, max(1, n_rows)))
    width = (hi - lo) / n_bins if hi > lo else 1.0
    hist = np.zeros(n_bins, dtype=np.int64)
    for _, time in blocks:
        at = np.clip(((time - lo) / width).astype(np.int64), 0, n_bins - 1)
        hist += np.bincount(at, minlength=n_bins)
    target = max(1, block_rows // BUCKETS_PER_BLOCK)
    cum = np.cumsum(hist)
    # a bucket ends after the bin where the rows so far pass the next multiple of target
    cut = np.unique(np.searchsorted(cum, np.arange(target, n_rows, target), side="left") + 1)
    inner = lo + cut[cut < n_bins] * width
    return np.concatenate([[-np.inf], np.unique(inner[inner > lo]), [np.inf]])


def _runs(blocks, edges: np.ndarray):
    """((first row, length, bucket) of every run of consecutive rows in one bucket, rows
    per bucket), block by block."""
    firsts, lengths, buckets = [], [], []
    counts = np.zeros(edges.size - 1, dtype=np.int64)
    for start, time in blocks:
        bucket = np.searchsorted(edges, time, side="right") - 1
        counts += np.bincount(bucket, minlength=counts.size)
        at = np.flatnonzero(np.diff(bucket) != 0) + 1
        run_at = np.concatenate([[0], at])
        firsts.append(start + run_at)
        lengths.append(np.diff(np.concatenate([run_at, [bucket.size]])))
        buckets.append(bucket[run_at])
    return (np.concatenate(firsts).astype(np.int64), np.concatenate(lengths).astype(np.int64),
            np.concatenate(buckets).astype(np.int32)), counts
