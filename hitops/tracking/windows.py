"""Per-sample SNR and the smoothing windows that follow from it (docs/tracking.md).

Per-sample SNR: from SIGMA (or WEIGHT = 1/SIGMA^2) when the reference set has
informative values, rho(t) = A / sigma, A estimated over the valid
visibilities within +-window samples from the mean power,
A^2 = <|V|^2> - 2 sigma^2, which does not depend on how fast the phase moves
inside the window; otherwise from the data: |<exp(i (phi_{t+1} - phi_t))>| = m^2,
m the mean resultant length of one noisy unit phasor, inverted through
:func:`hitops.tracking.theory.mean_resultant_length`.

Windows: the half-window of each sample is the theory's smallest one that
keeps the expected slips of a track below target
(:func:`hitops.tracking.theory.recommended_half_window`) at the sample's SNR
and (local) coherence time.
"""

from __future__ import annotations

import functools
from typing import Optional

import numpy as np

from . import theory
from .options import half_window_for, two_digits


def running_sum(values: np.ndarray, half_window) -> np.ndarray:
    """Sum over +-``half_window`` samples along the last axis (clipped at the ends).

    ``half_window``: an int, or an int array (n_time,) giving each time its own
    half-window (e.g. short where turbulence is fast, at low elevation).
    """
    n = values.shape[-1]
    csum = np.concatenate([np.zeros(values.shape[:-1] + (1,), values.dtype),
                           np.cumsum(values, axis=-1)], axis=-1)
    half = np.maximum(np.broadcast_to(np.asarray(half_window, dtype=np.int64), (n,)), 0)
    hi = np.minimum(np.arange(n) + half + 1, n)
    lo = np.maximum(np.arange(n) - half, 0)
    return csum[..., hi] - csum[..., lo]


@functools.lru_cache(maxsize=1)
def _resultant_table():
    """(rho, m(rho)) on a grid, to invert the mean resultant length by interpolation."""
    rho = np.concatenate([np.linspace(0.02, 1, 50), np.linspace(1.02, 12, 200)])
    m = np.array([theory.mean_resultant_length(r, 1001) for r in rho])
    return rho, m


def per_sample_snr(vis: np.ndarray, valid: np.ndarray, sigma: Optional[np.ndarray],
                   window: int) -> np.ndarray:
    """Per-sample SNR estimate of each regular series (n, L); NaN where unknown."""
    v = np.where(valid, vis, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        if sigma is not None:
            n = running_sum(valid.astype(np.float64), window)   # valid samples per window
            # incoherent: <|V|^2> = A^2 + 2 sigma^2 whatever the phase does inside the
            # window (a coherent |<V>| would fall where turbulence is fast, at low
            # elevation, and ask for longer windows exactly where they must be short)
            s2 = running_sum(np.where(valid, sigma, 0.0) ** 2, window) / n
            power = running_sum(np.abs(v) ** 2, window) / n
            rho = np.sqrt(np.clip(power - 2.0 * s2, 0, None) / s2)
        else:
            unit = np.where(valid, v / np.where(valid, np.abs(v), 1), 0)
            pair = unit[:, 1:] * np.conj(unit[:, :-1])
            pair = np.concatenate([pair, np.zeros((pair.shape[0], 1), pair.dtype)], axis=1)
            pair_ok = np.concatenate([valid[:, 1:] & valid[:, :-1],
                                      np.zeros((valid.shape[0], 1), bool)], axis=1)
            m2 = np.abs(running_sum(pair, window)) / running_sum(pair_ok.astype(np.float64), window)
            grid_rho, grid_m = _resultant_table()
            rho = np.interp(np.sqrt(np.clip(m2, 0, 1)), grid_m, grid_rho)
    return np.where(valid, rho, np.nan)


def half_windows(rho, coherence_time, dt: float = 1.0, widest: int = 200) -> np.ndarray:
    """Per-sample half-windows (int64) from per-sample SNR and (local) coherence time (s).

    ``rho`` and ``coherence_time`` broadcast together.  The theory
    (:func:`hitops.tracking.theory.recommended_half_window`) is evaluated once per
    distinct pair after rounding both to 2 significant digits (cached).  A sample
    whose SNR estimate is 0 (no signal left) gets the widest window its t_c
    allows, at most ``widest``; unknown (non-finite) inputs give 1.
    """
    rho, t_c = np.broadcast_arrays(np.asarray(rho, dtype=np.float64),
                                   np.asarray(coherence_time, dtype=np.float64))
    out = np.ones(rho.shape, np.int64)
    ok = np.isfinite(rho) & (rho > 0) & np.isfinite(t_c) & (t_c > 0)
    if ok.any():
        # each pair as one complex number: NumPy sorts complex values by their real, then
        # their imaginary part, so the distinct pairs and each sample's index are those of
        # np.unique(axis=0) on the stacked pairs, 4x faster (that one compares rows as
        # bytes: 1.1 s against 0.24 s per 1.4 x 10^6 samples, a 10^6-row chunk's two
        # correlations; 11.6 s of a 10^7-row smooth-tracker run went there)
        keys = two_digits(rho[ok]) + 1j * two_digits(np.maximum(t_c[ok], dt))
        # the SNR is a running mean, so neighbouring samples mostly share their rounded
        # pair: the distinct pairs are looked up among the first samples of each run of
        # equal keys, and each run takes its first sample's window
        first = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
        unique, inverse = np.unique(keys[first], return_inverse=True)
        values = np.array([half_window_for(float(k.real), float(k.imag), dt) for k in unique],
                          np.int64)
        out[ok] = np.repeat(values[inverse.ravel()], np.diff(np.append(first, keys.size)))
    low = np.isfinite(rho) & (rho <= 0) & np.isfinite(t_c)
    out[low] = np.clip(((t_c[low] / dt - 1) // 2).astype(np.int64), 1, widest)
    return out
