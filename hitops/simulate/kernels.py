"""Numba kernels of the simulator (pure: inputs are never modified)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def corrupt_visibilities(model, ant1, ant2, time_index, station_phase, parallel_hand,
                         noise, sigma):
    """Visibilities (n_row, n_corr) complex64 of a model seen through station phases plus noise.

    V[r, c] = model[r] exp(i (phi[ant1, t] - phi[ant2, t]))  for parallel hands,
              0                                               for cross hands,
    plus sigma[r] (noise[r, c, 0] + i noise[r, c, 1]) when ``noise`` has rows
    (pass an array of shape (0, n_corr, 2) for noise-free data).
    """
    n_row = model.shape[0]
    n_corr = parallel_hand.shape[0]
    out = np.empty((n_row, n_corr), dtype=np.complex64)
    with_noise = noise.shape[0] == n_row
    for r in range(n_row):
        t = time_index[r]
        dphi = station_phase[ant1[r], t] - station_phase[ant2[r], t]
        v = model[r] * complex(np.cos(dphi), np.sin(dphi))
        for c in range(n_corr):
            value = v if parallel_hand[c] else 0j
            if with_noise:
                value += sigma[r] * complex(noise[r, c, 0], noise[r, c, 1])
            out[r, c] = value
    return out
