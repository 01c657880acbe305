"""Theory of phase-wrap tracking on a noisy phasor.

Conventions.  A visibility at the reference band is V = A exp(i phi) + noise,
with complex Gaussian noise of standard deviation ``s`` in each of its real
and imaginary parts; the per-sample SNR is ``rho = A / s`` (the usual
VLBI definition, rho = |V| eta_q sqrt(2 dnu dt) / sqrt(SEFD_p SEFD_q); see
:mod:`hitops.tracking.stations`).  The noise phase theta = arg(1 + noise/A)
lies in (-pi, pi].

Exact per-step failure of the Itoh condition.  Naive tracking compares
consecutive wrapped phases; it counts correctly as long as the step of the
*noisy unwrapped* phase, delta + theta_2 - theta_1 (delta: the true step),
lies in (-pi, pi).  With theta_1, theta_2 independent, the failure
probability is

    P(delta) = int p(t1) [F(t1 - delta - pi) + 1 - F(t1 - delta + pi)] dt1,

where p is the phase density of a constant plus circular complex Gaussian
noise (S. O. Rice 1944, Bell Syst. Tech. J. 23, 282; Davenport & Root 1958,
*Random Signals and Noise*, ch. 8; Thompson, Moran & Swenson,
*Interferometry and Synthesis in Radio Astronomy*, chapter on the
statistics of visibility amplitude and phase):

    p(theta) = exp(-rho^2/2) / (2 pi)
             + rho cos(theta) / (2 sqrt(2 pi)) exp(-rho^2 sin^2(theta) / 2)
               [1 + erf(rho cos(theta) / sqrt 2)],

and F its cumulative distribution on (-pi, pi].  For delta = 0 this gives
3.42e-3 (rho = 2), 9.32e-5 (3), 1.22e-6 (4), 7.09e-9 (5).  The Gaussian
small-noise form, erfc(pi / (2 sigma)) with sigma = 1/rho, is 8.8e-6 at
rho = 2, too optimistic by a factor ~400, because the true phase density has
a floor exp(-rho^2/2)/(2 pi) that a Gaussian lacks.

Each failure changes the count by one and persists: the count after it is
off by one for the rest of the track (a later failure in the other direction
can cancel it).  In phase-wrap counting each persistent error leaves a
2 pi eps step in the 230 GHz residual (Lee et al., fpt-arbitrary-ratios).

Smoothed-phasor tracking (see :mod:`hitops.tracking.smooth_kernel`) unwraps the
phase of the sum S of W unit phasors.  Consecutive sums differ by at most
two unit vectors, so the smoothed phase can jump by more than pi only when
|S| <= 2; :func:`smoothed_slip_bound` bounds that probability with a
Gaussian model of S.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from hitops.errors import InputError

TWO_PI = 2.0 * np.pi

#: variance of a Kolmogorov (H = 5/6) phase about its mean over a window of
#: length W, in units of (W / t_c)^(5/3): (1/2)(1/W^2) int int D = 9/88
WINDOW_VARIANCE_COEFF = 9.0 / 88.0

#: error variance of predicting x(t+g) from x(t) and x(t-g) by linear
#: extrapolation, in units of D(g) = (g/t_c)^(5/3): 2 - (2^(5/3) - 2) = 4 - 2^(5/3)
LINEAR_PREDICTION_COEFF = 4.0 - 2.0 ** (5.0 / 3.0)

_erf = np.vectorize(math.erf, otypes=[np.float64])


def _check_rho(rho: float) -> float:
    rho = float(rho)
    if not np.isfinite(rho) or rho < 0:
        raise InputError(f"per-sample SNR must be a finite number >= 0, got {rho!r}")
    return rho


def phase_noise_pdf(theta, rho: float) -> np.ndarray:
    """Density of theta = arg(1 + n/A) on (-pi, pi] at per-sample SNR ``rho``."""
    rho = _check_rho(rho)
    theta = np.asarray(theta, dtype=np.float64)
    c = np.cos(theta)
    return (np.exp(-0.5 * rho * rho) / TWO_PI
            + rho * c / (2.0 * math.sqrt(TWO_PI)) * np.exp(-0.5 * (rho * np.sin(theta)) ** 2)
            * (1.0 + _erf(rho * c / math.sqrt(2.0))))


def _phase_grid(rho: float, n_grid: int):
    """Grid on [-pi, pi], the density there, and the lower and upper tail masses.

    The two tails are accumulated from their own ends, so tiny probabilities
    (1e-12 at rho = 5) are not lost to cancellation in 1 - F.
    """
    theta = np.linspace(-np.pi, np.pi, n_grid)
    pdf = phase_noise_pdf(theta, rho)
    h = theta[1] - theta[0]
    panel = 0.5 * h * (pdf[1:] + pdf[:-1])
    lower = np.concatenate([[0.0], np.cumsum(panel)])                 # F(theta)
    upper = np.concatenate([np.cumsum(panel[::-1])[::-1], [0.0]])     # 1 - F(theta)
    norm = lower[-1]
    return theta, pdf / norm, lower / norm, upper / norm


def itoh_failure_probability(rho: float, step: float = 0.0, n_grid: int = 20001) -> float:
    """Exact probability that one naive tracking step fails.

    ``step`` is the true phase step between the two samples (rad).  Failure
    means |step + theta_2 - theta_1| > pi for independent noise phases.
    """
    rho = _check_rho(rho)
    theta, pdf, lower, upper = _phase_grid(rho, n_grid)
    # P(theta_2 < t1 - step - pi) + P(theta_2 > t1 - step + pi)
    below = np.interp(theta - step - np.pi, theta, lower, left=0.0, right=1.0)
    above = np.interp(theta - step + np.pi, theta, upper, left=1.0, right=0.0)
    integrand = pdf * (below + above)
    h = theta[1] - theta[0]
    return float(h * (np.sum(integrand) - 0.5 * (integrand[0] + integrand[-1])))


def itoh_failure_probability_turbulent(rho: float, step_sigma: float, n_hermite: int = 24) -> float:
    """Failure probability averaged over Gaussian true steps of rms ``step_sigma`` (rad).

    For Kolmogorov turbulence sampled every dt, step_sigma = (dt/t_c)^(5/6)
    (:func:`kolmogorov_step_sigma`).
    """
    if step_sigma <= 0:
        return itoh_failure_probability(rho)
    nodes, weights = np.polynomial.hermite_e.hermegauss(n_hermite)
    values = [itoh_failure_probability(rho, step_sigma * x) for x in nodes]
    return float(np.dot(weights, values) / math.sqrt(TWO_PI))


def gaussian_failure_probability(rho: float) -> float:
    """The small-noise Gaussian form erfc(pi/(2 sigma)), sigma = 1/rho (too optimistic)."""
    rho = _check_rho(rho)
    return math.erfc(math.pi * rho / 2.0)


@functools.lru_cache(maxsize=4096)
def mean_resultant_length(rho: float, n_grid: int = 4001) -> float:
    """E[cos theta]: the expected length of one unit phasor along the signal."""
    theta, pdf, _, _ = _phase_grid(_check_rho(rho), n_grid)
    integrand = pdf * np.cos(theta)
    h = theta[1] - theta[0]
    return float(h * (np.sum(integrand) - 0.5 * (integrand[0] + integrand[-1])))


@functools.lru_cache(maxsize=4096)
def mean_sin_squared(rho: float, n_grid: int = 4001) -> float:
    """E[sin^2 theta]: the variance of one unit phasor across the signal direction."""
    theta, pdf, _, _ = _phase_grid(_check_rho(rho), n_grid)
    integrand = pdf * np.sin(theta) ** 2
    h = theta[1] - theta[0]
    return float(h * (np.sum(integrand) - 0.5 * (integrand[0] + integrand[-1])))


def kolmogorov_step_sigma(dt: float, coherence_time: float) -> float:
    """rms true phase step sqrt(D(dt)) = (dt/t_c)^(5/6) rad for a Kolmogorov screen."""
    if coherence_time <= 0 or dt <= 0:
        raise InputError(f"dt and coherence time must be > 0 (got dt={dt}, t_c={coherence_time})")
    return (dt / coherence_time) ** (5.0 / 6.0)


def window_coherence(window_s: float, coherence_time: float) -> float:
    """Expected |mean of exp(i phi)| over a window for Kolmogorov phase (Gaussian approx)."""
    var = WINDOW_VARIANCE_COEFF * (window_s / coherence_time) ** (5.0 / 3.0)
    return math.exp(-0.5 * var)


def smoothed_slip_bound(rho: float, window: int, coherence_samples: float) -> float:
    """Approximate upper bound on the per-step slip probability of the smoothed track.

    S, the sum of ``window`` unit phasors, is modelled as complex Gaussian with
    mean mu = W m C (m: mean resultant length, C: turbulent coherence over the
    window) and variance s^2 = W E[sin^2 theta] across it.  A slip needs
    |S| <= 2; P(|S| <= 2) <= (4 / (2 s^2)) exp(-(mu - 2)^2 / (2 s^2)) for mu > 2.
    """
    if window < 1:
        raise InputError(f"window must be >= 1 sample, got {window}")
    m = mean_resultant_length(rho)
    coh = window_coherence(window, coherence_samples)
    mu = window * m * coh
    s2 = max(window * mean_sin_squared(rho), 1e-300)
    if mu <= 2.0:
        return 1.0
    return min(1.0, 2.0 / s2 * math.exp(-((mu - 2.0) ** 2) / (2.0 * s2)))


def recommended_half_window(rho: float, coherence_time: float, dt: float = 1.0,
                            n_steps: int = 43200, target_slips: float = 1e-3,
                            max_half_window: int = 200) -> int:
    """Smallest half-window h (window 2h+1 samples) meeting ``target_slips`` per track.

    The window never exceeds the reference-band coherence time (beyond it the
    turbulent phase decorrelates inside the window).  At high SNR the answer is
    1; at rho = 2 and t_c = 33 s it is a few samples.
    """
    t_c_samples = coherence_time / dt
    cap = max(1, min(max_half_window, int((t_c_samples - 1) // 2)))
    for half in range(1, cap + 1):
        if smoothed_slip_bound(rho, 2 * half + 1, t_c_samples) * n_steps <= target_slips:
            return half
    return cap


def local_coherence_time(coherence_time_zenith: float, sin_elevation) -> np.ndarray:
    """Coherence time at elevation el: t_c sin(el)^(3/5) (phase variance grows with airmass)."""
    sin_el = np.clip(np.asarray(sin_elevation, dtype=np.float64), 1e-3, 1.0)
    return coherence_time_zenith * sin_el ** 0.6


def gap_bridge_failure_probability(gap_s: float, coherence_time: float, noise_rad: float = 0.0) -> float:
    """Probability that the lobe predicted across a gap of ``gap_s`` seconds is wrong.

    Linear extrapolation of a Kolmogorov phase over g from a baseline of the same
    length leaves an error variance (4 - 2^(5/3)) (g/t_c)^(5/3); ``noise_rad`` adds
    the rms error of the smoothed phases used for the prediction.  The lobe is
    wrong when the prediction error exceeds pi.
    """
    var = LINEAR_PREDICTION_COEFF * (gap_s / coherence_time) ** (5.0 / 3.0) + noise_rad ** 2
    if var <= 0:
        return 0.0
    return math.erfc(math.pi / math.sqrt(2.0 * var))


def recommended_max_gap(coherence_time: float, dt: float = 1.0, max_failure: float = 1e-4) -> int:
    """Longest gap (samples) bridged with failure probability below ``max_failure``."""
    gap = 0
    while gap < 100000 and gap_bridge_failure_probability((gap + 1) * dt, coherence_time) < max_failure:
        gap += 1
    return gap


#: variance of the difference of the means of two adjacent W-sample windows of a
#: Kolmogorov phase, in units of (W/t_c)^(5/3):
#: (2^(11/3) - 2)/((8/3)(11/3)) - 2/((8/3)(11/3))
ADJACENT_WINDOW_COEFF = (2.0 ** (11.0 / 3.0) - 4.0) / ((8.0 / 3.0) * (11.0 / 3.0))


def jump_statistic_sigma(rho: float, jump_window: int, coherence_time: float, dt: float = 1.0) -> float:
    """rms (rad) of the jump statistic arg(conj(L) R) without a jump.

    L and R are the sums of ``jump_window`` unit phasors before and from a
    sample.  Thermal part: each mean phase has variance E[sin^2 theta]/(W m^2)
    (m: mean resultant length of one unit phasor); turbulent part: the
    difference of adjacent window means of a Kolmogorov phase,
    ADJACENT_WINDOW_COEFF (W dt / t_c)^(5/3).
    """
    m = mean_resultant_length(rho)
    thermal_var = 2.0 * mean_sin_squared(rho) / (jump_window * max(m * m, 1e-12))
    turbulent_var = ADJACENT_WINDOW_COEFF * (jump_window * dt / coherence_time) ** (5.0 / 3.0)
    return math.sqrt(thermal_var + turbulent_var)


def jump_threshold(rho: float, jump_window: int, coherence_time: float, dt: float = 1.0,
                   n_sigma: float = 6.0, floor: float = 1.5) -> float:
    """Threshold (rad) on the jump statistic: ``n_sigma`` times its rms, at least ``floor``."""
    return float(max(floor, n_sigma * jump_statistic_sigma(rho, jump_window, coherence_time, dt)))


def recommended_jump_params(rho: float, coherence_time: float, dt: float = 1.0,
                            n_sigma: float = 6.0, floor: float = 1.5,
                            max_threshold: float = 0.8 * math.pi) -> tuple[int, float]:
    """(jump_window, jump_threshold) minimising the threshold; threshold 0 (off) if it
    would exceed ``max_threshold``: then turbulence and noise hide jumps of pi."""
    best = (3, float("inf"))
    for window in range(3, 61):
        thr = jump_threshold(rho, window, coherence_time, dt, n_sigma, floor)
        if thr < best[1]:
            best = (window, thr)
    if best[1] > max_threshold:
        return best[0], 0.0
    return best


def slip_phase_step(ratio: float) -> float:
    """Phase step (rad, in (-pi, pi]) one missed wrap leaves at the target band: 2 pi eps.

    eps = R - floor(R) is formed from R itself so that R within 1e-6 of an
    integer from either side gives a step within 2 pi 1e-6 of zero.
    """
    if not np.isfinite(ratio) or ratio <= 0:
        raise InputError(f"frequency ratio R must be a finite number > 0, got {ratio!r}")
    eps = ratio - math.floor(ratio)
    step = TWO_PI * eps
    return float(step - TWO_PI * round(step / TWO_PI))
