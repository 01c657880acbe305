"""Radiometer physics: system temperature, SEFD and per-visibility sigma.

Shared by the simulator's thermal noise (hitops.simulate), the tracking
thresholds (hitops.tracking.stations) and the forecasts (hitops.forecast);
it sits below all of them and imports nothing of hitops.

Radiometer equation for a complex visibility (Thompson, Moran & Swenson
2017, ch. 6; the form used by MeqSilhouette and Simelane et al. 2024):

    sigma_pq = sqrt(SEFD_p SEFD_q / (2 dnu dt)) / eta_q          [Jy]

the rms of each of the real and imaginary parts, with eta_q = 0.88 for
2-bit sampling.  SEFD = 2 k T_sys / A_eff with A_eff = eta_A pi D^2 / 4, and
T_sys referred to above the atmosphere:

    T_sys = (T_rx + T_atm (1 - exp(-tau X))) exp(tau X),   X = 1/sin(el)

where tau is the zenith opacity and T_atm the physical temperature of the
absorbing layer (plane-parallel atmosphere).
"""

from __future__ import annotations

import numpy as np

BOLTZMANN = 1.380649e-23      # J/K (exact, SI 2019)
JY = 1e-26                    # W m^-2 Hz^-1


def airmass(elevation: np.ndarray, min_elevation_deg: float = 1.0) -> np.ndarray:
    """Plane-parallel airmass 1/sin(el), with el floored at ``min_elevation_deg``."""
    floor = np.sin(np.radians(min_elevation_deg))
    return 1.0 / np.maximum(np.sin(elevation), floor)


def system_temperature(t_rx: float, t_atm: float, tau: float, air_mass: np.ndarray) -> np.ndarray:
    """T_sys (K) above the atmosphere at the given airmass."""
    opacity = tau * air_mass
    return (t_rx + t_atm * (1.0 - np.exp(-opacity))) * np.exp(opacity)


def sefd(t_sys: np.ndarray, diameter: float, aperture_efficiency: float) -> np.ndarray:
    """System equivalent flux density (Jy)."""
    area = aperture_efficiency * np.pi * diameter ** 2 / 4.0
    return 2.0 * BOLTZMANN * t_sys / area / JY


def baseline_sigma(sefd_p: np.ndarray, sefd_q: np.ndarray, bandwidth_hz: float,
                   integration_s: float, eta_q: float = 0.88) -> np.ndarray:
    """Per-visibility rms (Jy) of the real and of the imaginary part.

    ``bandwidth_hz`` is the bandwidth one visibility integrates: the channel
    width for channelised data (each channel's noise is independent).
    """
    return np.sqrt(sefd_p * sefd_q / (2.0 * bandwidth_hz * integration_s)) / eta_q
