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


@numba.njit(cache=True, nogil=True)
def _runs(tgt_grid, keys, data, flag, flag_row, phasor, delay, chan_offset, off_data,
          point_model, fill):
    """Per-channel sums over runs of equal key in time; sweep 0 counts the runs."""
    n_bl, n_corr, n_time = keys.shape
    n_chan = data.shape[1]
    n_runs = 0
    r = -1
    index = np.zeros((0, 3), np.int64)
    sums = np.zeros((0, n_chan), np.complex128)
    counts = np.zeros((0, n_chan), np.int64)
    for sweep in range(2 if fill else 1):
        if sweep == 1:
            index = np.zeros((n_runs, 3), np.int64)
            sums = np.zeros((n_runs, n_chan), np.complex128)
            counts = np.zeros((n_runs, n_chan), np.int64)
        for b in range(n_bl):
            for c in range(n_corr):
                cur = -1
                for t in range(n_time):
                    row = tgt_grid[b, t]
                    key = keys[b, c, t]
                    p = complex(phasor[row, c]) if row >= 0 else 0j
                    if row < 0 or key < 0 or p == 0j or flag_row[row]:
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
                    tau = delay[row, c]
                    for k in range(n_chan):
                        v = data[row, k, c]
                        if flag[row, k, c] or not usable(v):
                            continue
                        out = v * p * complex(math.cos(-TWO_PI * chan_offset[k] * tau),
                                              math.sin(-TWO_PI * chan_offset[k] * tau))
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
                        sums[r, k] += u / mag
                        counts[r, k] += 1
    return index, sums, counts


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
    point = off_data is None
    args = (np.ascontiguousarray(tgt_grid, np.int64), np.ascontiguousarray(keys, np.int64),
            np.ascontiguousarray(data), np.ascontiguousarray(flag),
            np.ascontiguousarray(flag_row), np.ascontiguousarray(phasor),
            np.ascontiguousarray(delay, np.float64),
            np.ascontiguousarray(chan_offset, np.float64),
            np.ascontiguousarray(data if point else off_data), point)
    index, sums, counts = _runs(*args, True)
    if index.shape[0] == 0:
        return index, sums, counts
    uniq, inverse = np.unique(index, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    merged = np.zeros((uniq.shape[0], sums.shape[1]), np.complex128)
    merged_counts = np.zeros((uniq.shape[0], sums.shape[1]), np.int64)
    np.add.at(merged, inverse, sums)
    np.add.at(merged_counts, inverse, counts)
    return uniq.astype(np.int64), merged, merged_counts
