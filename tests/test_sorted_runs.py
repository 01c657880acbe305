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
