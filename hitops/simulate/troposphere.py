"""Kolmogorov tropospheric phase as fractional Brownian motion.

A frozen Kolmogorov screen blown past a station gives a temporal phase
structure function D(dt) = <(phi(t+dt) - phi(t))^2> = (dt/t_c)^(5/3) rad^2
(Tatarskii 1961; Treuhaft & Lanyi 1987, Radio Sci. 22, 251 for the radio
form; MeqSilhouette, Blecher et al. 2017, MNRAS 464, 143 for its use in EHT
simulation).  That is a fractional Brownian motion (fBm) with Hurst exponent
H = 5/6.  Its increments on a regular grid are fractional Gaussian noise
(fGn), a *stationary* sequence, so they can be drawn exactly with circulant
embedding (Davies & Harte 1987, Biometrika 74, 95; Dietrich & Newsam 1997,
SIAM J. Sci. Comput. 18, 1088): embed the fGn autocovariance in a circulant
matrix of size 2n, whose eigenvalues are one FFT, and colour complex white
noise with their square roots.  The real and imaginary parts of one FFT are
two independent exact samples, so stations are generated in pairs.
For fGn the embedding is non-negative definite for every H (Craigmile 2003,
J. Time Ser. Anal. 24, 505), so the method never needs padding or clipping
beyond round-off.

Alternatives kept for the error-against-run-time benchmark
(benchmarks/bench_simulate.py):

* :func:`fbm_cholesky` - dense Cholesky of the fBm covariance: exact but
  O(n^3) time, O(n^2) memory and ill-conditioned as n grows;
* :func:`fbm_fft_powerlaw` - plain FFT synthesis of a 1/f^(2H+1) power
  spectrum on the observation length: loses power at frequencies below
  1/T, so long-lag structure is too low;
* :func:`random_walk` - cumulative sum of white increments: D grows as dt,
  not dt^(5/3).

Frequency and airmass scaling (see docs/simulate.md):
phase at frequency nu is (nu/nu0) times the phase at nu0 (non-dispersive),
so t_c(nu) = t_c(nu0) (nu/nu0)^(-6/5); the structure-function coefficient
of each increment is multiplied by the airmass 1/sin(el) at that time
(variance of the path through a thin turbulent layer grows with path length).
"""

from __future__ import annotations

import numpy as np

#: Hurst exponent of a Kolmogorov temporal phase structure function
HURST_KOLMOGOROV = 5.0 / 6.0


def fgn_autocovariance(n: int, hurst: float) -> np.ndarray:
    """Autocovariance gamma(k), k = 0..n-1, of unit-variance fGn."""
    k = np.arange(n, dtype=np.float64)
    two_h = 2.0 * hurst
    return 0.5 * (np.abs(k + 1.0) ** two_h - 2.0 * k ** two_h + np.abs(k - 1.0) ** two_h)


def circulant_eigenvalues(n: int, hurst: float) -> np.ndarray:
    """Eigenvalues (length 2n) of the circulant embedding of n fGn samples."""
    gamma = fgn_autocovariance(n + 1, hurst)
    # first row of the 2n circulant: gamma(0..n), gamma(n-1..1)
    row = np.concatenate([gamma, gamma[-2:0:-1]])
    eig = np.fft.fft(row).real
    # round-off can leave tiny negative values; the embedding is nnd for fGn
    if eig.min() < -1e-8 * eig.max():
        raise RuntimeError(f"circulant embedding not non-negative (min eigenvalue {eig.min()})")
    return np.clip(eig, 0.0, None)


def fgn_circulant(n: int, n_series: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """``n_series`` independent unit-variance fGn sequences of length ``n``, shape (n_series, n).

    Exact (Davies-Harte): each complex FFT of coloured white noise gives two
    independent series, its real and imaginary parts.
    """
    if n <= 0 or n_series <= 0:
        return np.zeros((max(n_series, 0), max(n, 0)))
    eig = circulant_eigenvalues(n, hurst)
    m = eig.size                      # 2n
    n_pairs = (n_series + 1) // 2
    white = rng.standard_normal((n_pairs, m)) + 1j * rng.standard_normal((n_pairs, m))
    coloured = np.fft.fft(white * np.sqrt(eig / m), axis=-1)[:, :n]
    series = np.empty((2 * n_pairs, n))
    series[0::2] = coloured.real
    series[1::2] = coloured.imag
    return series[:n_series]


def fbm_circulant(n: int, n_series: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """fBm with unit one-step structure function, sampled at 0..n-1 (starts at 0)."""
    out = np.zeros((n_series, n))
    if n > 1:
        out[:, 1:] = np.cumsum(fgn_circulant(n - 1, n_series, hurst, rng), axis=-1)
    return out


def fbm_cholesky(n: int, n_series: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """Exact fBm by dense Cholesky of its covariance (O(n^3); for the benchmark only)."""
    t = np.arange(1, n, dtype=np.float64)
    two_h = 2.0 * hurst
    cov = 0.5 * (t[:, None] ** two_h + t[None, :] ** two_h
                 - np.abs(t[:, None] - t[None, :]) ** two_h)
    chol = np.linalg.cholesky(cov)
    out = np.zeros((n_series, n))
    out[:, 1:] = rng.standard_normal((n_series, n - 1)) @ chol.T
    return out


def fbm_fft_powerlaw(n: int, n_series: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """Plain FFT synthesis of a power-law spectrum P(f) ~ f^-(2H+1) on n samples.

    Normalised so the one-step structure function is 1 on average; the
    periodic record has no power below 1/n, so long lags are underestimated.
    """
    freqs = np.fft.rfftfreq(n)
    amp = np.zeros_like(freqs)
    amp[1:] = freqs[1:] ** (-(2.0 * hurst + 1.0) / 2.0)
    spectrum = amp * (rng.standard_normal((n_series, freqs.size))
                      + 1j * rng.standard_normal((n_series, freqs.size)))
    series = np.fft.irfft(spectrum, n=n, axis=-1)
    # normalise with the expected one-step increment variance of this spectrum
    # irfft: x_j = (2/n) sum_k Re(X_k e^{i w_k j}), E|X_k|^2 = 2 a_k^2
    step_var = 8.0 * np.sum(amp[1:] ** 2 * (1.0 - np.cos(2.0 * np.pi * freqs[1:]))) / n ** 2
    series /= np.sqrt(step_var)
    return series - series[:, :1]


def random_walk(n: int, n_series: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """Cumulative sum of unit white increments (D(dt) = dt: the wrong exponent)."""
    out = np.zeros((n_series, n))
    out[:, 1:] = np.cumsum(rng.standard_normal((n_series, n - 1)), axis=-1)
    return out


GENERATORS = {
    "circulant": fbm_circulant,
    "cholesky": fbm_cholesky,
    "fft_powerlaw": fbm_fft_powerlaw,
    "random_walk": random_walk,
}


def structure_function(series: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Ensemble- and time-averaged D(lag) of series (n_series, n) at integer ``lags``."""
    return np.array([np.mean((series[:, lag:] - series[:, :-lag]) ** 2) for lag in lags])


def station_phases(n_time: int, dt: float, coherence_time: np.ndarray, airmass: np.ndarray,
                   start_index: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Unwrapped tropospheric phase (rad) of each station at the coherence frequency.

    ``coherence_time`` (n_station,) or (n_station, n_time) is the zenith t_c in
    seconds at the frequency the phases refer to (per sample: the increment from
    sample j to j+1 uses t_c[:, j]); ``airmass`` (n_station, n_time) is 1/sin(el)
    on the time grid of step ``dt``.  The increment between samples j and j+1
    has structure-function coefficient airmass[j] * (dt/t_c)^(5/3), i.e. the
    local coherence time is t_c * sin(el)^(3/5).  Each station's phase is zero
    at ``start_index`` (its first sample above its elevation limit), as in the
    paper's simulations (n_p(t_p) = 0).
    """
    coherence_time = np.asarray(coherence_time, dtype=np.float64)
    n_station = coherence_time.shape[0]
    phases = np.zeros((n_station, n_time))
    if n_time < 2:
        return phases
    unit_steps = fgn_circulant(n_time - 1, n_station, HURST_KOLMOGOROV, rng)
    scale = (dt / coherence_time) ** (5.0 / 6.0)             # sqrt of (dt/t_c)^(5/3)
    # a coherence time per sample (n_station, n_time), e.g. from a wind that changes
    # between MERRA-2 analyses, scales each increment by its own local value
    scale = scale[:, :-1] if scale.ndim == 2 else scale[:, None]
    steps = unit_steps * scale * np.sqrt(airmass[:, :-1])
    phases[:, 1:] = np.cumsum(steps, axis=-1)
    phases -= phases[np.arange(n_station), start_index][:, None]
    return phases
