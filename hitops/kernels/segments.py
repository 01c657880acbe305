"""Per-segment sums of the n0 offset step and the shift by 2 pi eps k: numba kernels.

The first pass of a calibrate run with the n0 step sums, per (baseline,
correlation, segment key), exp(i (Phi_ref - Phi_out)) of its calibrated samples
(Phi_ref: the offset reference or model phase; Phi_out: the transferred output
phase).  :func:`segment_run_sums` does it inside a baseline group's transfer task
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


class SegmentSums(NamedTuple):
    """Sums of exp(i (Phi_ref - Phi_out)) per (baseline, correlation, segment key), sorted."""

    index: np.ndarray     # (m, 3) int64 baseline, correlation, key
    sums: np.ndarray      # (m,) complex128
    counts: np.ndarray    # (m,) int64 samples


@numba.njit(cache=True, nogil=True)
def _segment_runs(keys, tgt_phase, phasor, calibrated, off_phase, off_valid, fill):
    """Sums of exp(i (Phi_ref - Phi_out)) over runs of equal segment key in time.

    keys/tgt_phase/off_phase/off_valid (n_bl, n_corr, n_time), phasor/calibrated
    (n_bl, n_time, n_corr).  With ``fill`` False only the number of runs is
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
                    if key < 0 or not (calibrated[b, t, c] and off_valid[b, c, t]):
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
                    p = phasor[b, t, c]
                    d = off_phase[b, c, t] - (tgt_phase[b, c, t] + math.atan2(p.imag, p.real))
                    sums[r] += complex(math.cos(d), math.sin(d))
                    counts[r] += 1
    return index, sums, counts
    r = -1
    for b in range(n_bl):
        for c in range(n_corr):
            cur = -1
            for t in range(n_time):
                key = keys[b, c, t]
                if key < 0 or not (calibrated[b, t, c] and off_valid[b, c, t]):
                    continue
                if key != cur:
                    r += 1
                    cur = key
                    index[r, 0] = b
                    index[r, 1] = c
                    index[r, 2] = key
                p = phasor[b, t, c]
                d = off_phase[b, c, t] - (tgt_phase[b, c, t] + math.atan2(p.imag, p.real))
                sums[r] += complex(math.cos(d), math.sin(d))
                counts[r] += 1
    return index, sums, counts


def segment_run_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid) -> SegmentSums:
    """The sums per distinct (baseline, correlation, key) from the gridded phases."""
    args = (np.ascontiguousarray(keys, np.int64), np.ascontiguousarray(tgt_phase, np.float64),
            np.ascontiguousarray(phasor), np.ascontiguousarray(calibrated),
            np.ascontiguousarray(off_phase, np.float64), np.ascontiguousarray(off_valid))
    return _merge_runs(*_segment_runs(*args, True))


def _merge_runs(index, sums, counts) -> SegmentSums:
    """The runs of one (baseline, correlation, key) added up: one entry each, sorted."""
    if index.shape[0] == 0:
        return SegmentSums(index, sums, counts)
    uniq, inverse = np.unique(index, axis=0, return_inverse=True)
    inverse = inverse.ravel()
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


@numba.njit(cache=True, nogil=True)
def _segment_row_runs(tgt_rows, keys, tgt_vis, phasor, calibrated, off_vis, off_ok, fill):
    """:func:`_segment_runs` reading row-ordered arrays through the chunk's row grid."""
    n_bl, n_corr, n_time = keys.shape
    n_runs = 0
    r = -1
    index = np.zeros((0, 3), np.int64)
    sums = np.zeros(0, np.complex128)
    counts = np.zeros(0, np.int64)
    for sweep in range(2 if fill else 1):
        if sweep == 1:
            index = np.zeros((n_runs, 3), np.int64)
            sums = np.zeros(n_runs, np.complex128)
            counts = np.zeros(n_runs, np.int64)
        for b in range(n_bl):
            for c in range(n_corr):
                cur = -1
                for t in range(n_time):
                    row = tgt_rows[b, t]
                    key = keys[b, c, t]
                    if row < 0 or key < 0 or not (calibrated[row, c] and off_ok[row, c]):
                        continue
                    o = off_vis[row, c]
                    if not (math.isfinite(o.real) and math.isfinite(o.imag)) or (o.real == 0 and o.imag == 0):
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
                    v = tgt_vis[row, c] * phasor[row, c]
                    d = math.atan2(o.imag, o.real) - math.atan2(v.imag, v.real)
                    sums[r] += complex(math.cos(d), math.sin(d))
                    counts[r] += 1
    return index, sums, counts


def segment_row_sums(tgt_rows, keys, tgt_vis, phasor, calibrated, off_vis, off_ok) -> SegmentSums:
    """Sums of exp(i (Phi_ref - Phi_out)) per (baseline, correlation, segment key), sorted,
    from the chunk's row-ordered target visibilities, output phasors and reference (or
    model) visibilities; the driver's form of :func:`segment_run_sums` (no phase grids)."""
    return _merge_runs(*_segment_row_runs(
        np.ascontiguousarray(tgt_rows), np.ascontiguousarray(keys, np.int64),
        np.ascontiguousarray(tgt_vis), np.ascontiguousarray(phasor),
        np.ascontiguousarray(calibrated), np.ascontiguousarray(off_vis),
        np.ascontiguousarray(off_ok), True))
