"""The tracking threshold in station terms (SEFD, system temperature, opacity).

Radiometer equation for one visibility of a baseline p-q (Thompson, Moran &
Swenson, *Interferometry and Synthesis in Radio Astronomy*, 3rd ed., ch. 6
and 9; GUIDE.md section 1):

    sigma = sqrt(SEFD_p SEFD_q / (2 dnu dt)) / eta_q        (per real/imag part)
    rho   = S eta_q sqrt(2 dnu dt) / sqrt(SEFD_p SEFD_q)    (per-sample SNR)

with eta_q = 0.88 for 2-bit sampling, SEFD = 2 k Tsys* / (eta_A A), and the
system temperature referred to above the atmosphere

    Tsys* = [T_rx + T_atm (1 - exp(-tau / sin el))] exp(tau / sin el).

``eta_A`` (aperture efficiency) and ``T_atm`` (effective atmospheric
temperature) are inputs: the paper's values came from the ngehtsim database,
which is not available here.  Defaults: eta_A = 0.6 (typical of mm dishes),
T_atm = 260 K.
"""

from __future__ import annotations

import math

import numpy as np

from hitops import radiometer as noise
from hitops.errors import InputError

ETA_2BIT = 0.88


def system_temperature(t_rx: float, tau_zenith: float, elevation_deg: float, t_atm: float = 260.0) -> float:
    """Tsys* (K) above the atmosphere for receiver temperature ``t_rx`` and zenith opacity.

    Same formula as the simulator's noise (hitops.radiometer), which it calls.
    """

    if not 0 < elevation_deg <= 90:
        raise InputError(f"elevation must be in (0, 90] deg, got {elevation_deg}")
    airmass = 1.0 / math.sin(math.radians(elevation_deg))
    return float(noise.system_temperature(t_rx, t_atm, tau_zenith, np.float64(airmass)))


def sefd(tsys: float, diameter_m: float, aperture_efficiency: float = 0.6) -> float:
    """System equivalent flux density (Jy) of a dish of ``diameter_m`` (hitops.radiometer.sefd)."""

    return float(noise.sefd(np.float64(tsys), diameter_m, aperture_efficiency))


def per_sample_snr(flux_jy: float, sefd_p: float, sefd_q: float, bandwidth_hz: float, dt_s: float,
                   eta_q: float = ETA_2BIT) -> float:
    """rho = S eta_q sqrt(2 dnu dt) / sqrt(SEFD_p SEFD_q)."""
    return flux_jy * eta_q * math.sqrt(2.0 * bandwidth_hz * dt_s) / math.sqrt(sefd_p * sefd_q)


def max_sefd_product(rho_min: float, flux_jy: float, bandwidth_hz: float, dt_s: float,
                     eta_q: float = ETA_2BIT) -> float:
    """Largest sqrt(SEFD_p SEFD_q) (Jy) that keeps the per-sample SNR >= ``rho_min``."""
    return flux_jy * eta_q * math.sqrt(2.0 * bandwidth_hz * dt_s) / rho_min


def max_opacity(sefd_limit_jy: float, t_rx: float, diameter_m: float, elevation_deg: float,
                aperture_efficiency: float = 0.6, t_atm: float = 260.0) -> float:
    """Largest zenith opacity at which the station's SEFD stays below ``sefd_limit_jy``.

    NaN if even tau = 0 exceeds the limit.  Bisection on the monotonic Tsys*(tau).
    """
    def station_sefd(tau):
        return sefd(system_temperature(t_rx, tau, elevation_deg, t_atm), diameter_m, aperture_efficiency)

    if station_sefd(0.0) > sefd_limit_jy:
        return float("nan")
    lo, hi = 0.0, 5.0
    if station_sefd(hi) <= sefd_limit_jy:
        return hi
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if station_sefd(mid) <= sefd_limit_jy:
            lo = mid
        else:
            hi = mid
    return lo


def rho_for_slip_rate(slips_per_track: float, n_steps: int = 43200, step_sigma: float = 0.0) -> float:
    """Per-sample SNR at which naive tracking expects ``slips_per_track`` slips (exact theory)."""
    from hitops.tracking.theory import itoh_failure_probability_turbulent

    lo, hi = 0.5, 12.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if itoh_failure_probability_turbulent(mid, step_sigma) * (n_steps - 1) > slips_per_track:
            lo = mid
        else:
            hi = mid
    return hi


def antenna_snr(baseline_rho: np.ndarray) -> float:
    """Approximate SNR of one antenna's phase solution from its baselines' per-sample SNRs.

    The antenna phase combines its baselines (weights ~ rho^2), so its
    variance is ~ 1/sum(rho_pq^2): rho_p ~ sqrt(sum rho_pq^2) (high-SNR limit).
    """
    baseline_rho = np.asarray(baseline_rho, dtype=np.float64)
    return float(np.sqrt(np.sum(baseline_rho ** 2)))
