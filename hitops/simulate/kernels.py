"""Numba kernels of the simulator (pure: inputs are never modified)."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def corrupt_channels(model, ant1, ant2, time_index, phase_ref, chan_scale, inst_phase,
                     inst_delay, chan_offset, parallel_hand, noise, sigma):
    """Visibilities (n_row, n_chan, n_corr) complex64 of one spectral window.

    The troposphere is an excess path L_p(t) per station: its phase at channel k is
    2 pi nu_k L_p / c = phase_ref[p, t] * chan_scale[k] (phase_ref the phase at the
    coherence frequency nu_0, chan_scale = nu_k / nu_0).  With instrumental terms
    (``inst_phase`` with rows), station p adds inst_phase[p, t] + 2 pi chan_offset[k]
    inst_delay[p, t] (chan_offset = nu_k - nu_band, delays in seconds):

    V[r, k, c] = model[r, k] exp(i (phi_p - phi_q))  for parallel hands, 0 for cross hands,

    plus sigma[r] (noise[r, k, c, 0] + i noise[r, k, c, 1]) when ``noise`` has rows
    (an array of shape (0, n_chan, n_corr, 2) gives noise-free data).  Each station's
    phase is scaled before the difference is taken, in that order, so one channel at
    the band's frequency reproduces the single-channel simulator bit for bit.
    """
    n_row, n_chan = model.shape
    n_corr = parallel_hand.shape[0]
    out = np.empty((n_row, n_chan, n_corr), dtype=np.complex64)
    with_noise = noise.shape[0] == n_row
    with_inst = inst_phase.shape[0] > 0
    for r in range(n_row):
        t = time_index[r]
        p = ant1[r]
        q = ant2[r]
        for k in range(n_chan):
            dphi = phase_ref[p, t] * chan_scale[k] - phase_ref[q, t] * chan_scale[k]
            if with_inst:
                dphi += (inst_phase[p, t] - inst_phase[q, t]
                         + 2.0 * math.pi * chan_offset[k] * (inst_delay[p, t] - inst_delay[q, t]))
            v = model[r, k] * complex(np.cos(dphi), np.sin(dphi))
            for c in range(n_corr):
                value = v if parallel_hand[c] else 0j
                if with_noise:
                    value += sigma[r] * complex(noise[r, k, c, 0], noise[r, k, c, 1])
                out[r, k, c] = value
    return out
