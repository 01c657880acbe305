"""Frequency phase transfer kernels over a (baseline, time) layout.

Notation of the paper (fpt-arbitrary-ratios.tex, Methods): phi_cal is the
reference-band phase, Phi the target-band phase, R = nu_t / nu_r = r + eps.

* CFPT  (eq. cfpt):  Phi - R*phi_cal
* PWC   (eq. pwc):   Phi - R*phi_cal + 2*pi*eps*n(t), n(t) the reference wrap count
* CWU:               wrap(unwrap(Phi) - R*unwrap(phi_cal)); with unwrap(x) = x - 2*pi*n_x(t)

Every method is applied as one unit phasor per cell, so the output is
V_target * phasor: the amplitude is kept and averaged channels all get the
same correction.  Rows are not copied onto a grid: ``rows[b, t]`` holds the
row index (or -1) of each (baseline, time) cell and the kernels read the row
arrays through it.  Kernels never mutate their inputs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

PWC, CFPT, CWU = 0, 1, 2
METHOD_CODES = {"pwc": PWC, "cfpt": CFPT, "cwu": CWU}
TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True)
def wrap_phase(x):
    """Wrap radians to [-pi, pi)."""
    return (x + math.pi) % TWO_PI - math.pi


@numba.njit(cache=True, nogil=True, inline="always")
def usable(v):
    """A visibility takes part in FPT only when finite and non-zero (zero = no data)."""
    re = v.real
    im = v.imag
    return math.isfinite(re) and math.isfinite(im) and not (re == 0.0 and im == 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def arg(v):
    """The phase of ``v`` in float64, whatever its precision: numba types ``math.atan2``
    of a complex64's parts as float32 (the C library's atan2f), 1e-7 rad coarse."""
    return math.atan2(np.float64(v.imag), np.float64(v.real))


@numba.njit(cache=True, nogil=True)
def gather_parts(rows, vis, ok, swapped, corr_map):
    """The real and imaginary parts of each (baseline, correlation) series in time order,
    in float64, swapped rows conjugated, and their validity (the arguments and the rule
    of :func:`gather_phase`, whose kernel this is).

    Returns re, im (n_bl, n_corr, n_time) float64 (0 where invalid) and valid
    (n_bl, n_corr, n_time) bool.
    """
    n_bl, n_time = rows.shape
    n_corr = corr_map.shape[1]
    re = np.zeros((n_bl, n_corr, n_time))
    im = np.zeros((n_bl, n_corr, n_time))
    valid = np.zeros((n_bl, n_corr, n_time), dtype=np.bool_)
    for b in range(n_bl):
        for t in range(n_time):
            row = rows[b, t]
            if row < 0:
                continue
            swap = swapped[row]
            for c in range(n_corr):
                ci = corr_map[1 if swap else 0, c]
                if ci < 0 or not ok[row, ci]:
                    continue
                v = vis[row, ci]
                if not usable(v):
                    continue
                re[b, c, t] = v.real
                # the conjugate's phase is the phase negated, for every value atan2 takes
                # (its sign follows the imaginary part's, signed zeros included)
                im[b, c, t] = -v.imag if swap else v.imag
                valid[b, c, t] = True
    return re, im, valid


def gather_phase(rows, vis, ok, swapped, corr_map):
    """Phase series of each (baseline, correlation) in time order.

    rows: (n_bl, n_time) int64 row index or -1; vis: (n_row, n_corr_in) complex;
    ok: (n_row, n_corr_in) bool; swapped: (n_row,) bool, True when the row's
    antenna order is reversed with respect to the baseline (its phase is
    negated, i.e. the visibility conjugated); corr_map: (2, n_corr) int64, the
    input correlation of each output correlation for unswapped (0) and
    swapped (1) rows, -1 when there is none.

    Returns phase (n_bl, n_corr, n_time) float64 (NaN where invalid) and
    valid (n_bl, n_corr, n_time) bool: unflagged, finite, non-zero samples.
    The arctangent is NumPy's float64 loop over the gathered parts: vectorised where
    the CPU allows (about 2 ns per sample with AVX-512 here, against 18 ns for the C
    library's scalar atan2 in a numba loop; docs/performance.md, "What one process here
    cannot go below").
    """
    re, im, valid = gather_parts(rows, vis, ok, swapped, corr_map)
    phase = np.arctan2(im, re, out=re)
    phase[~valid] = np.nan
    return phase, valid


@numba.njit(cache=True, nogil=True)
def gather_valid(rows, vis, ok):
    """Validity (n_bl, n_corr, n_time) of target samples, without computing phases.

    Same rule as :func:`gather_phase` for unswapped rows with the identity
    correlation map; PWC and CFPT need only this from the target band.
    """
    n_bl, n_time = rows.shape
    n_corr = vis.shape[1]
    valid = np.zeros((n_bl, n_corr, n_time), dtype=np.bool_)
    for b in range(n_bl):
        for t in range(n_time):
            row = rows[b, t]
            if row < 0:
                continue
            for c in range(n_corr):
                if ok[row, c] and usable(vis[row, c]):
                    valid[b, c, t] = True
    return valid


@numba.njit(cache=True, nogil=True)
def transfer_phasors(tgt_rows, tgt_phase, tgt_valid, ref_phase, ref_valid, ref_wraps,
                     tgt_wraps, ratio, eps, method, offset, scan_of_time):
    """Unit phasors that turn the target visibility into the FPT-calibrated one.

    tgt_rows: (n_bl, n_time) target row index or -1 (cells without a target
    row get no output); tgt_phase/tgt_valid, ref_phase/ref_valid/ref_wraps:
    (n_bl, n_corr, n_time) series; tgt_wraps: the target wrap counts (CWU
    only; any shape otherwise); method: PWC, CFPT or CWU; offset:
    (n_bl, n_corr, n_scan) phase added by the n0 offset step (PWC, CWU);
    scan_of_time: (n_time,) scan index of each time.

    Returns phasor (n_bl, n_time, n_corr) complex64 (0 where the cell cannot
    be calibrated) and calibrated (n_bl, n_time, n_corr) bool: the target
    and reference samples were both valid.
    """
    n_bl, n_corr, n_time = ref_phase.shape
    phasor = np.zeros((n_bl, n_time, n_corr), dtype=np.complex64)
    calibrated = np.zeros((n_bl, n_time, n_corr), dtype=np.bool_)
    two_pi_eps = TWO_PI * eps
    for b in range(n_bl):
        for t in range(n_time):
            if tgt_rows[b, t] < 0:
                continue
            s = scan_of_time[t]
            for c in range(n_corr):
                if not (ref_valid[b, c, t] and tgt_valid[b, c, t]):
                    continue
                phi = ref_phase[b, c, t]
                if method == PWC:
                    theta = -(ratio * phi - two_pi_eps * ref_wraps[b, c, t]) + offset[b, c, s]
                elif method == CFPT:
                    theta = -ratio * phi
                else:
                    big_phi = tgt_phase[b, c, t]
                    unwrapped_tgt = big_phi - TWO_PI * tgt_wraps[b, c, t]
                    unwrapped_ref = phi - TWO_PI * ref_wraps[b, c, t]
                    result = wrap_phase(unwrapped_tgt - ratio * unwrapped_ref + offset[b, c, s])
                    theta = result - big_phi
                phasor[b, t, c] = complex(math.cos(theta), math.sin(theta))
                calibrated[b, t, c] = True
    return phasor, calibrated


@numba.njit(cache=True, nogil=True)
def sample_cause_counts(tgt_rows, ref_rows, tgt_valid, ref_valid, calibrated):
    """Target samples and why some are not calibrated, in one pass: int64 (5,) of
    [samples, target invalid, no reference row, reference invalid, other uncalibrated].

    tgt_rows, ref_rows (n_bl, n_time) row index or -1; tgt_valid, ref_valid
    (n_bl, n_corr, n_time); calibrated (n_bl, n_time, n_corr).  Each sample of a cell
    with a target row counts under the first cause that holds, in this order.
    """
    n_bl, n_corr, n_time = ref_valid.shape
    counts = np.zeros(5, dtype=np.int64)
    for b in range(n_bl):
        for t in range(n_time):
            if tgt_rows[b, t] < 0:
                continue
            has_ref = ref_rows[b, t] >= 0
            counts[0] += n_corr
            for c in range(n_corr):
                if not tgt_valid[b, c, t]:
                    counts[1] += 1
                elif not has_ref:
                    counts[2] += 1
                elif not ref_valid[b, c, t]:
                    counts[3] += 1
                elif not calibrated[b, t, c]:
                    counts[4] += 1
    return counts


@numba.njit(cache=True, nogil=True)
def offset_sums(tgt_phase, phasor, calibrated, off_phase, off_valid, scan_of_time, n_scan):
    """Sum of exp(i*(Phi_ref - Phi_out)) per (baseline, correlation, scan).

    Phi_out is the calibrated phase (target phase + arg(phasor)); Phi_ref the
    phase of the offset-reference column.  The argument of the sum is the
    circular mean offset of the paper's n0 step (Results: Arg(z_bar)).
    Returns (sums complex128 (n_bl, n_corr, n_scan), counts int64 same shape).
    """
    n_bl, n_corr, n_time = tgt_phase.shape
    sums = np.zeros((n_bl, n_corr, n_scan), dtype=np.complex128)
    counts = np.zeros((n_bl, n_corr, n_scan), dtype=np.int64)
    for b in range(n_bl):
        for t in range(n_time):
            s = scan_of_time[t]
            for c in range(n_corr):
                if not (calibrated[b, t, c] and off_valid[b, c, t]):
                    continue
                p = phasor[b, t, c]
                out_phase = tgt_phase[b, c, t] + arg(p)
                d = off_phase[b, c, t] - out_phase
                sums[b, c, s] += complex(math.cos(d), math.sin(d))
                counts[b, c, s] += 1
    return sums, counts


@numba.njit(cache=True, nogil=True)
def row_grid(n_bl, n_time, bl, time_index):
    """(n_bl, n_time) int64: the index of the row in each (baseline, time) cell, or -1.

    bl, time_index (n_row,): each row's cell (negative values count from the end, as
    numpy indexing does; a cell given twice holds its last row).
    """
    grid = np.full((n_bl, n_time), -1, dtype=np.int64)
    for i in range(bl.size):
        b = bl[i] + n_bl if bl[i] < 0 else bl[i]
        t = time_index[i] + n_time if time_index[i] < 0 else time_index[i]
        if not (0 <= b < n_bl and 0 <= t < n_time):
            raise IndexError("a row's baseline or time is outside the chunk's grid")
        grid[b, t] = i
    return grid


@numba.njit(cache=True, nogil=True)
def scatter_rows(tgt_rows, grid, n_row, fill):
    """Gather (n_bl, n_time, n_corr) cell values back to (n_row, n_corr) row order."""
    n_bl, n_time, n_corr = grid.shape
    out = np.full((n_row, n_corr), fill, dtype=grid.dtype)
    for b in range(n_bl):
        for t in range(n_time):
            row = tgt_rows[b, t]
            if row >= 0:
                for c in range(n_corr):
                    out[row, c] = grid[b, t, c]
    return out
