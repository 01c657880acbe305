"""Per-sample slip model of the forecast: weather -> SNR and coherence time -> slips per hour.

For a baseline p-q at 86 GHz, source elevation el (airmass X = 1/sin el):

* sky and system temperature from the weather (zenith opacity tau, sky
  brightness Tb): T_sys = (T_rx + T_eff (1 - exp(-tau X))) exp(tau X) with
  T_eff = Tb / (1 - exp(-tau)); SEFD = 2 k T_sys / (eta_A pi D^2 / 4);
* per-sample SNR rho = S eta_q sqrt(2 dnu dt) / sqrt(SEFD_p SEFD_q)
  (hitops.tracking.stations.per_sample_snr);
* station coherence time at 86 GHz and elevation el:
  t_c = (r0 / v) (86/230)^(-6/5) sin(el)^(3/5) (frozen screen: t_c(230) = r0/v;
  non-dispersive scaling; airmass scaling as in the simulator);
* baseline phase step rms over dt: sigma^2 = (dt/t_c,p)^(5/3) + (dt/t_c,q)^(5/3);
  baseline coherence time t_c,pq = dt sigma^(-6/5);
* naive tracking fails a step with the exact probability
  P(rho, sigma) = :func:`hitops.tracking.theory.itoh_failure_probability_turbulent`
  (Rice phase density, Gaussian true steps), tabulated once on a (rho, sigma)
  grid and interpolated in log P; per hour: 1 - (1 - P)^(3600/dt);
* the smoothed tracker: window from
  :func:`hitops.tracking.windows.half_windows`, per-step slip bound
  :func:`hitops.tracking.theory.smoothed_slip_bound` (an upper bound).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from .. import radiometer as noise_mod
from ..tracking import theory
from ..tracking.windows import half_windows

ETA_Q = 0.88
RHO_GRID = np.geomspace(0.2, 12.0, 61)
SIGMA_GRID = np.concatenate([[0.0], np.geomspace(0.02, 2.5, 15)])
FLOOR = 1e-300


@lru_cache(maxsize=1)
def failure_table() -> np.ndarray:
    """log10 of the exact per-step naive failure probability on (RHO_GRID, SIGMA_GRID)."""
    out = np.empty((RHO_GRID.size, SIGMA_GRID.size))
    for i, rho in enumerate(RHO_GRID):
        for j, sig in enumerate(SIGMA_GRID):
            if sig == 0:
                p = theory.itoh_failure_probability(rho, 0.0, n_grid=3001)
            else:
                nodes, weights = np.polynomial.hermite_e.hermegauss(12)
                p = float(np.dot(weights, [theory.itoh_failure_probability(rho, sig * x, n_grid=3001)
                                           for x in nodes]) / math.sqrt(2 * math.pi))
            out[i, j] = math.log10(max(p, FLOOR))
    return out


def naive_failure_probability(rho, step_sigma) -> np.ndarray:
    """Per-step failure probability of naive tracking, bilinear in (log rho, sigma) on the table.

    Outside the grid: rho below 0.2 is treated as 0.2 (failure ~0.4 per step: tracking is
    hopeless there anyway); at or above 12 the probability (< 1e-30) is returned as 0;
    sigma above 2.5 rad is treated as 2.5.
    """
    table = failure_table()
    rho = np.clip(np.asarray(rho, dtype=np.float64), RHO_GRID[0], RHO_GRID[-1])
    sig = np.clip(np.asarray(step_sigma, dtype=np.float64), 0.0, SIGMA_GRID[-1])
    x = np.interp(np.log(rho), np.log(RHO_GRID), np.arange(RHO_GRID.size))
    y = np.interp(sig, SIGMA_GRID, np.arange(SIGMA_GRID.size))
    i0 = np.clip(np.floor(x).astype(int), 0, RHO_GRID.size - 2)
    j0 = np.clip(np.floor(y).astype(int), 0, SIGMA_GRID.size - 2)
    fx, fy = x - i0, y - j0
    logp = ((1 - fx) * (1 - fy) * table[i0, j0] + fx * (1 - fy) * table[i0 + 1, j0]
            + (1 - fx) * fy * table[i0, j0 + 1] + fx * fy * table[i0 + 1, j0 + 1])
    p = 10.0 ** logp
    # above the grid's SNR the probability is below 1e-30: report it as 0
    return np.where(np.asarray(rho) >= RHO_GRID[-1], 0.0, p)


def sefd_86(t_rx, efficiency, diameter, tau, tb, elevation_deg) -> np.ndarray:
    """SEFD (Jy) at the source elevation from zenith opacity and sky temperature."""
    tau = np.asarray(tau, dtype=np.float64)
    t_eff = np.asarray(tb) / -np.expm1(-np.maximum(tau, 1e-12))
    air = 1.0 / math.sin(math.radians(elevation_deg))
    t_sys = noise_mod.system_temperature(t_rx, t_eff, tau, air)
    return noise_mod.sefd(t_sys, diameter, efficiency)


def station_coherence_86(wind, r0, elevation_deg, min_wind=0.1) -> np.ndarray:
    """Local coherence time (s) of one station's 86 GHz phase at the source elevation."""
    t_c230 = r0 / np.maximum(np.asarray(wind, dtype=np.float64), min_wind)
    return t_c230 * (86.0 / 230.0) ** (-6.0 / 5.0) * math.sin(math.radians(elevation_deg)) ** 0.6


def baseline_terms(flux, bandwidth_hz, dt, sefd_p, sefd_q, tc_p, tc_q):
    """(rho, step_sigma, baseline t_c) arrays for paired samples of two stations."""
    rho = flux * ETA_Q * np.sqrt(2.0 * bandwidth_hz * dt) / np.sqrt(sefd_p * sefd_q)
    step_var = (dt / tc_p) ** (5.0 / 3.0) + (dt / tc_q) ** (5.0 / 3.0)
    return rho, np.sqrt(step_var), dt * step_var ** (-0.6)


def per_hour(p_step, dt) -> np.ndarray:
    """Probability of at least one failure in an hour of independent steps."""
    return -np.expm1(np.log1p(-np.clip(p_step, 0.0, 1.0 - 1e-16)) * (3600.0 / dt))


def smooth_slip_probability(rho, tc_bl, dt) -> np.ndarray:
    """Per-step slip bound of the smoothed tracker with its recommended window."""
    rho = np.asarray(rho, dtype=np.float64)
    tc_bl = np.asarray(tc_bl, dtype=np.float64)
    half = half_windows(rho, tc_bl, dt)
    keys = np.stack([np.round(np.log(np.maximum(rho, 1e-3)), 2), np.round(np.log(tc_bl / dt), 2),
                     half], axis=1)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    values = np.array([theory.smoothed_slip_bound(math.exp(r), int(2 * h + 1), math.exp(t))
                       for r, t, h in unique])
    return values[inverse.ravel()]
