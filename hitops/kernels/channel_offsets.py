"""The n0 step's sums per target channel (issue 26): numba kernels.

A PWC output counted from n'(t0) = 0 while the true count starts at n0 is off by
2*pi*R_j*n0 (mod 2*pi) in target channel j.  One channel sees only
2*pi*eps*n0, which cannot tell n0 from n0 + 43 at R = 230/86; across a wide
window the offsets of the channels differ like a delay n0/nu_ref, which can
(:func:`hitops.kernels.wideband.channel_offset_scores`).  So the first pass sums,
per series key (scan or tracking segment) and target channel,

    z_j = sum over samples of exp(i (Phi_ref,j - Phi_out,j)),

with Phi_out,j the phase the writer gives channel j (the cell's phasor at the
window centre times exp(-2*pi*i*(nu_j - nu_0)*delay), hitops/calibrate/channels.py)
and Phi_ref,j the offset reference's channel j (0 for ``--offset-model point``).
The kernels do not change their inputs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .fpt import TWO_PI, usable


def _series_of_cells(tgt_grid, keys, phasor, flag_row):
    """Which sum each calibrated (baseline, correlation, time) cell adds to.

    Returns (cell_series (n_bl, n_corr, n_time) int64, -1 for none; index (m, 3) int64
    baseline, correlation, key of each sum, sorted)."""
    n_bl, n_corr, n_time = keys.shape
    rows = np.broadcast_to(tgt_grid[:, None, :], keys.shape)
    has_row = rows >= 0
    safe = np.where(has_row, rows, 0)
    calibrated = (has_row & (keys >= 0) & ~flag_row[safe]
                  & (phasor[safe, np.arange(n_corr)[None, :, None]] != 0))
    cells = np.flatnonzero(calibrated.ravel())
    key = keys.ravel()[cells]
    series = cells // n_time                    # baseline * n_corr + correlation
    key_values, key_index = np.unique(key, return_inverse=True)
    ids, inverse = np.unique(series * key_values.size + key_index.ravel(), return_inverse=True)
    cell_series = np.full(keys.size, -1, np.int64)
    cell_series[cells] = inverse.ravel()
    pair = ids // key_values.size
    index = np.stack([pair // n_corr, pair % n_corr, key_values[ids % key_values.size]], axis=1)
    return cell_series.reshape(keys.shape), index.astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _accumulate(tgt_grid, cell_series, n_series, data, flag, phasor, delay, chan_offset,
                off_data, point_model):
    """sums (n_series, n_chan) of exp(i (Phi_ref - Phi_out)) and their counts."""
    n_bl, n_corr, n_time = cell_series.shape
    n_chan = data.shape[1]
    sums = np.zeros((n_series, n_chan), np.complex128)
    counts = np.zeros((n_series, n_chan), np.int64)
    for b in range(n_bl):
        for t in range(n_time):
            row = tgt_grid[b, t]
            for c in range(n_corr):
                s = cell_series[b, c, t]
                if s < 0:
                    continue
                p = complex(phasor[row, c])
                tau = delay[row, c]
                for k in range(n_chan):
                    v = data[row, k, c]
                    if flag[row, k, c] or not usable(v):
                        continue
                    turn = -TWO_PI * chan_offset[k] * tau
                    out = v * p * complex(math.cos(turn), math.sin(turn))
                    if point_model:
                        u = out.conjugate()
                    else:
                        o = off_data[row, k, c]
                        if not usable(o):
                            continue
                        u = o * out.conjugate()
                    mag = abs(u)
                    if mag == 0.0 or not math.isfinite(mag):
                        continue
                    sums[s, k] += u / mag
                    counts[s, k] += 1
    return sums, counts


def channel_offset_sums(tgt_grid, keys, data, flag, flag_row, phasor, delay, chan_offset,
                        off_data=None):
    """z_j and its sample count per distinct (baseline, correlation, key) and target channel.

    tgt_grid (n_bl, n_time) row index or -1; keys (n_bl, n_corr, n_time) int64 series key
    (scan index, or a tracker's segment key), -1 for none; data/flag (n_row, n_chan,
    n_corr) the target column and its flags, flag_row (n_row,); phasor (n_row, n_corr)
    the output phasor at the window centre (0: not calibrated) and delay (n_row, n_corr)
    seconds; chan_offset (n_chan,) nu_j - nu_0 Hz; off_data (n_row, n_chan, n_corr) the
    offset reference (a calibrated column or a model), None for a point model (phase 0).
    Returns (index (m, 3) int64 sorted, sums (m, n_chan) complex128, counts (m, n_chan)
    int64).
    """
    tgt_grid = np.ascontiguousarray(tgt_grid, np.int64)
    cell_series, index = _series_of_cells(tgt_grid, np.asarray(keys, np.int64),
                                          np.asarray(phasor), np.asarray(flag_row, bool))
    point = off_data is None
    sums, counts = _accumulate(
        tgt_grid, cell_series, index.shape[0], np.ascontiguousarray(data),
        np.ascontiguousarray(flag), np.ascontiguousarray(phasor),
        np.ascontiguousarray(delay, np.float64), np.ascontiguousarray(chan_offset, np.float64),
        np.ascontiguousarray(data if point else off_data), point)
    return index, sums, counts
