"""Distinct values and lookups for columns stored as a few ascending runs.

A Measurement Set's TIME column is ascending (time-ordered sets) or a few
dozen ascending runs, one per baseline (baseline-major sets such as those
written baseline by baseline).  NumPy's answers to "which distinct times,
how many rows each" and "where is each row's time in the list of distinct
times" sort or binary-search every row (np.unique, np.searchsorted: 40-80 ms
per 1.2 M rows here); walking the runs against the sorted list is linear.
Shuffled columns (many short runs) fall back to NumPy, see
:func:`hitops.io.match.distinct_counts`.  :func:`bucket_rows` groups the rows
of a table not in time order by time chunk, once, so that each chunk's rows
are found without a search over the whole column.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def count_runs(values):
    """Number of ascending runs (a new run starts where a value drops)."""
    if values.size == 0:
        return 0
    n_runs = 1
    for i in range(1, values.size):
        if values[i] < values[i - 1]:
            n_runs += 1
    return n_runs


@numba.njit(cache=True, nogil=True)
def run_distinct_counts(values):
    """Distinct values of the first run and their counts over all runs, and the rest.

    Returns (distinct, counts, extra): ``distinct`` the sorted distinct values
    of the first ascending run; ``counts`` how many values of the whole array
    equal each; ``extra`` the values of later runs that are not in
    ``distinct`` (with repeats).  Each later run is walked against
    ``distinct`` in step, so the cost is n + n_runs * n_distinct.
    """
    n = values.size
    end = 1 if n else 0
    while end < n and values[end] >= values[end - 1]:
        end += 1
    distinct = np.empty(end, dtype=values.dtype)
    n_distinct = 0
    for i in range(end):
        if n_distinct == 0 or values[i] != distinct[n_distinct - 1]:
            distinct[n_distinct] = values[i]
            n_distinct += 1
    distinct = distinct[:n_distinct].copy()
    counts = np.zeros(n_distinct, dtype=np.int64)
    extra = np.empty(n - end, dtype=values.dtype)
    n_extra = 0
    j = 0
    for i in range(n):
        v = values[i]
        if i > 0 and v < values[i - 1]:
            j = 0   # a new run: walk the distinct values from the start again
        while j < n_distinct and distinct[j] < v:
            j += 1
        if j < n_distinct and distinct[j] == v:
            counts[j] += 1
        else:
            extra[n_extra] = v
            n_extra += 1
    return distinct, counts, extra[:n_extra].copy()


@numba.njit(cache=True, nogil=True)
def lookup_sorted(values, table):
    """Index of each value in the ascending array ``table`` (exact match), -1 if absent.

    The search starts where the previous value was found and gallops from
    there, so ascending runs cost O(1) per value; any order stays correct
    (O(log n_table) per value at worst).
    """
    n_table = table.size
    out = np.empty(values.size, dtype=np.int64)
    j = 0
    for i in range(values.size):
        v = values[i]
        if n_table == 0:
            out[i] = -1
            continue
        if table[j] < v:
            # gallop forward: table[j] < v; find lo < hi with table[lo] < v <= table[hi]
            step = 1
            lo = j
            hi = j + 1
            while hi < n_table and table[hi] < v:
                lo = hi
                step *= 2
                hi = lo + step
            if hi > n_table:
                hi = n_table
        elif table[j] > v:
            step = 1
            hi = j
            lo = j - 1
            while lo >= 0 and table[lo] >= v:
                hi = lo
                step *= 2
                lo = hi - step
            if lo < -1:
                lo = -1
        else:
            out[i] = j
            continue
        # binary search in (lo, hi]: the first index with table[index] >= v
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if table[mid] < v:
                lo = mid
            else:
                hi = mid
        if hi < n_table and table[hi] == v:
            out[i] = hi
            j = hi
        else:
            out[i] = -1
            j = min(hi, n_table - 1)
    return out


@numba.njit(cache=True, nogil=True)
def bucket_rows(time, edges):
    """Rows grouped by time bucket [edges[k], edges[k+1]), ascending within each.

    Returns (order, start): bucket k's rows are order[start[k]:start[k+1]].
    One counting pass and one filling pass, int32 row numbers (4 bytes per row).
    """
    n_bucket = edges.size - 1
    bucket = np.searchsorted(edges, time, side="right") - 1
    start = np.zeros(n_bucket + 1, dtype=np.int64)
    for i in range(time.size):
        start[bucket[i] + 1] += 1
    for k in range(n_bucket):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(time.size, dtype=np.int32)
    for i in range(time.size):
        order[fill[bucket[i]]] = i
        fill[bucket[i]] += 1
    return order, start


@numba.njit(cache=True, nogil=True)
def time_order_places(at, scans, row_start, seen, time_scan):
    """Where a block of rows read in storage order goes in the (TIME, row number) order.

    ``at`` (n,): each row's index among the distinct times (ascending rows, so rows of
    one time arrive in the order they take); ``scans`` (n,): each row's SCAN_NUMBER;
    ``row_start``: the first position of each distinct time; ``seen``: rows of each
    time already placed by earlier blocks; ``time_scan``: the scan of the last row
    placed at each time so far.  Returns (positions, seen, time_scan) after the block;
    the inputs are not changed.
    """
    seen_after = seen.copy()
    scan_after = time_scan.copy()
    positions = np.empty(at.size, dtype=np.int64)
    for i in range(at.size):
        u = at[i]
        positions[i] = row_start[u] + seen_after[u]
        seen_after[u] += 1
        scan_after[u] = scans[i]
    return positions, seen_after, scan_after
