"""Count errors of a tracker against a known truth (tests and benchmarks).

A simulated track has a true unwrapped reference phase; the tracker's count
is right at a sample when ``ref_phase - 2 pi n`` lies within pi of it.
:func:`slip_errors` gives the error e = n - n_true per sample and
:func:`count_slips` splits its changes into persistent slips (each leaves a
2 pi eps step in the transferred phase) and transients (single outliers whose
own noise exceeded pi).
"""

from __future__ import annotations

import numba
import numpy as np

TWO_PI = 2.0 * np.pi


@numba.njit(cache=True, nogil=True)
def slip_errors(counts, ref_phase, valid, true_phase):
    """Count error e = n - n_true at every valid sample, against a true unwrapped phase.

    The true count is the lobe of ``ref_phase`` nearest ``true_phase`` (so a
    sample whose noise exceeds pi counts as an error).  Returns int64[n_time]
    with 0 where invalid; only its changes matter (n0 is arbitrary).
    """
    n_time = ref_phase.size
    err = np.zeros(n_time, np.int64)
    for i in range(n_time):
        if valid[i] and np.isfinite(ref_phase[i]):
            n_true = np.int64(np.round((ref_phase[i] - true_phase[i]) / TWO_PI))
            err[i] = counts[i] - n_true
    return err


@numba.njit(cache=True, nogil=True)
def count_slips(err, valid, max_transient=3):
    """(persistent slips, transient samples) of a count-error series.

    A transient is a run of at most ``max_transient`` valid samples whose
    error differs from the valid samples on both sides, which agree with each
    other: an outlier excursion (samples whose own noise exceeds pi), not a
    slip.  Transients are replaced by their neighbours' value; persistent
    slips are the sum of |changes| of the cleaned error between consecutive
    valid samples.
    """
    n_time = err.size
    m = 0
    for i in range(n_time):
        if valid[i]:
            m += 1
    e = np.empty(m, np.int64)
    k = 0
    for i in range(n_time):
        if valid[i]:
            e[k] = err[i]
            k += 1
    # runs of equal error
    run_start = np.empty(m + 1, np.int64)
    n_runs = 0
    for k in range(m):
        if k == 0 or e[k] != e[k - 1]:
            run_start[n_runs] = k
            n_runs += 1
    run_start[n_runs] = m
    cleaned = e.copy()
    transients = 0
    for r in range(1, n_runs - 1):
        length = run_start[r + 1] - run_start[r]
        before = cleaned[run_start[r] - 1]
        after = e[run_start[r + 1]]
        if length <= max_transient and before == after:
            for k in range(run_start[r], run_start[r + 1]):
                cleaned[k] = before
            transients += length
    slips = 0
    for k in range(1, m):
        slips += abs(cleaned[k] - cleaned[k - 1])
    return slips, transients
