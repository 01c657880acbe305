"""Per-segment sums of the n0 offset step and the shift by 2 pi eps k: numba kernels.

The first pass of a calibrate run with the n0 step sums, per (baseline,
correlation, segment key), exp(i (Phi_ref - Phi_out)) of its calibrated samples
(Phi_ref: the offset reference or model phase; Phi_out: the transferred output
phase).  :func:`segment_run_sums` does it inside a baseline batch's transfer task
on the gridded phases, :func:`segment_row_sums` in the driver on row-ordered
visibilities (a first pass that keeps its output).  :func:`shifted_rows` then
moves a kept output by exp(i 2 pi eps k) per segment instead of a second
transfer.  The kernels do not change their inputs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from numba import types
from numba.extending import overload

from .distinct import unique_rows
from .fpt import arg


class SegmentSums(NamedTuple):
    """Sums of exp(i (Phi_ref - Phi_out)) per (baseline, correlation, segment key), sorted."""

    index: np.ndarray     # (m, 3) int64 baseline, correlation, key
    sums: np.ndarray      # (m,) complex128
    counts: np.ndarray    # (m,) int64 samples


class GridSamples(NamedTuple):
    """A baseline batch's samples on its grid (the transfer task's form)."""

    tgt_phase: np.ndarray     # (n_bl, n_corr, n_time) float64 target phase
    phasor: np.ndarray        # (n_bl, n_time, n_corr) output phasor
    calibrated: np.ndarray    # (n_bl, n_time, n_corr) bool
    off_phase: np.ndarray     # (n_bl, n_corr, n_time) float64 offset reference/model phase
    off_valid: np.ndarray     # (n_bl, n_corr, n_time) bool


class RowSamples(NamedTuple):
    """A chunk's row-ordered samples read through its row grid (the driver's form)."""

    tgt_rows: np.ndarray      # (n_bl, n_time) row of each cell, -1: none
    tgt_vis: np.ndarray       # (n_row, n_corr) target visibilities
    phasor: np.ndarray        # (n_row, n_corr) output phasors
    calibrated: np.ndarray    # (n_row, n_corr) bool
    off_vis: np.ndarray       # (n_row, n_corr) offset reference/model visibilities
    off_ok: np.ndarray        # (n_row, n_corr) bool


# The two forms share one run-summing kernel (_segment_runs); what differs is how a
# cell's sample is reached and tested, chosen when numba compiles the kernel for the
# samples' type (numba.extending.overload).  Each form's arithmetic is written once,
# in the order the sums have always been taken, so the sums keep every bit.

def _usable(samples, b, c, t):
    """Whether cell (b, c, t) holds a sample to sum (numba only; see the overload)."""
    raise NotImplementedError("numba-compiled only")


def _phase_diff(samples, b, c, t):
    """Phi_ref - Phi_out of a usable cell (numba only; see the overload)."""
    raise NotImplementedError("numba-compiled only")


def _form(samples):
    """GridSamples or RowSamples, from the numba type of ``samples`` (else None)."""
    if isinstance(samples, types.BaseNamedTuple):
        return samples.instance_class
    return None


@overload(_usable, inline="always")
def _usable_impl(samples, b, c, t):
    if _form(samples) is GridSamples:
        def usable(samples, b, c, t):
            return samples.calibrated[b, t, c] and samples.off_valid[b, c, t]
        return usable
    if _form(samples) is RowSamples:
        def usable(samples, b, c, t):
            row = samples.tgt_rows[b, t]
            if row < 0 or not (samples.calibrated[row, c] and samples.off_ok[row, c]):
                return False
            o = samples.off_vis[row, c]
            return (math.isfinite(o.real) and math.isfinite(o.imag)
                    and not (o.real == 0 and o.imag == 0))
        return usable
    return None


@overload(_phase_diff, inline="always")
def _phase_diff_impl(samples, b, c, t):
    if _form(samples) is GridSamples:
        def phase_diff(samples, b, c, t):
            p = samples.phasor[b, t, c]
            return samples.off_phase[b, c, t] - (samples.tgt_phase[b, c, t] + arg(p))
        return phase_diff
    if _form(samples) is RowSamples:
        def phase_diff(samples, b, c, t):
            row = samples.tgt_rows[b, t]
            o = samples.off_vis[row, c]
            v = samples.tgt_vis[row, c] * samples.phasor[row, c]
            return arg(o) - arg(v)
        return phase_diff
    return None


@numba.njit(cache=True, nogil=True)
def _segment_runs(keys, samples, fill):
    """Sums of exp(i (Phi_ref - Phi_out)) over runs of equal segment key in time.

    keys (n_bl, n_corr, n_time); ``samples`` a :class:`GridSamples` or
    :class:`RowSamples`.  With ``fill`` False only the number of runs is
    counted; otherwise returns the runs (baseline, correlation, key), sums, counts.
    """
    n_bl, n_corr, n_time = keys.shape
    n_runs = 0
    r = -1
    index = np.zeros((0, 3), np.int64)
    sums = np.zeros(0, np.complex128)
    counts = np.zeros(0, np.int64)
    # sweep 0 counts the runs, sweep 1 fills them
    for sweep in range(2 if fill else 1):
        if sweep == 1:
            index = np.zeros((n_runs, 3), np.int64)
            sums = np.zeros(n_runs, np.complex128)
            counts = np.zeros(n_runs, np.int64)
        for b in range(n_bl):
            for c in range(n_corr):
                cur = -1
                for t in range(n_time):
                    key = keys[b, c, t]
                    if key < 0 or not _usable(samples, b, c, t):
                        continue
                    if key != cur:
                        cur = key
                        if sweep == 0:
                            n_runs += 1
                            continue
                        r += 1
                        index[r, 0] = b
                        index[r, 1] = c
                        index[r, 2] = key
                    elif sweep == 0:
                        continue
                    d = _phase_diff(samples, b, c, t)
                    sums[r] += complex(math.cos(d), math.sin(d))
                    counts[r] += 1
    return index, sums, counts


def segment_run_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid) -> SegmentSums:
    """The sums per distinct (baseline, correlation, key) from the gridded phases."""
    samples = GridSamples(np.ascontiguousarray(tgt_phase, np.float64),
                          np.ascontiguousarray(phasor), np.ascontiguousarray(calibrated),
                          np.ascontiguousarray(off_phase, np.float64),
                          np.ascontiguousarray(off_valid))
    return _merge_runs(*_segment_runs(np.ascontiguousarray(keys, np.int64), samples, True))


def _merge_runs(index, sums, counts) -> SegmentSums:
    """The runs of one (baseline, correlation, key) added up: one entry each, sorted."""
    if index.shape[0] == 0:
        return SegmentSums(index, sums, counts)
    uniq, inverse = unique_rows(index)
    out_sums = np.bincount(inverse, sums.real, uniq.shape[0]) \
        + 1j * np.bincount(inverse, sums.imag, uniq.shape[0])
    return SegmentSums(uniq.astype(np.int64), out_sums,
                       np.bincount(inverse, counts, uniq.shape[0]).astype(np.int64))


@numba.njit(cache=True, nogil=True)
def shifted_rows(tgt_rows, k, table, k_min, phasors):
    """A copy of ``phasors`` with out[row, c] = phasors[row, c] * table[k[b, c, t] - k_min]
    in every cell with a row and k != 0.

    tgt_rows (n_bl, n_time) row index or -1; k (n_bl, n_corr, n_time) integers added to
    the wrap counts; table complex64 exp(i 2 pi eps k) for k_min..; phasors (n_row,
    n_corr) the output phasors of one method.
    """
    out = phasors.copy()
    n_bl, n_corr, n_time = k.shape
    for b in range(n_bl):
        for t in range(n_time):
            row = tgt_rows[b, t]
            if row < 0:
                continue
            for c in range(n_corr):
                kk = k[b, c, t]
                if kk != 0:
                    out[row, c] = out[row, c] * table[kk - k_min]
    return out


def segment_row_sums(tgt_rows, keys, tgt_vis, phasor, calibrated, off_vis, off_ok) -> SegmentSums:
    """Sums of exp(i (Phi_ref - Phi_out)) per (baseline, correlation, segment key), sorted,
    from the chunk's row-ordered target visibilities, output phasors and reference (or
    model) visibilities; the driver's form of :func:`segment_run_sums` (no phase grids)."""
    samples = RowSamples(np.ascontiguousarray(tgt_rows), np.ascontiguousarray(tgt_vis),
                         np.ascontiguousarray(phasor), np.ascontiguousarray(calibrated),
                         np.ascontiguousarray(off_vis), np.ascontiguousarray(off_ok))
    return _merge_runs(*_segment_runs(np.ascontiguousarray(keys, np.int64), samples, True))
