"""Per-antenna, per-target-channel transfer of unwrapped reference solutions.

With u the unwrapped reference phase (``wraps.unwrap_solutions``) at nu_ref, the
table's CHAN_FREQ, the phase to remove from target channel k is

    phase_k = R_k * u,   R_k = nu_k / nu_ref,

which is the paper's PWC per channel: with u = phi + 2*pi*n and R_k = r_k + eps_k,
R_k*u = R_k*phi + 2*pi*r_k*n + 2*pi*eps_k*n, and 2*pi*r_k*n vanishes on a phasor.
Per-channel ratios on one reference phase are a phase plus a delay:

    R_k * u = R_c * u + 2*pi*(nu_k - nu_c) * u / (2*pi*nu_ref),

so one Fringe Jones row per target window carries them exactly: the phase R_c * u at
the window centre nu_c and the delay u / (2*pi*nu_ref) (CASA applycal evaluates
phase + 2*pi*delay*(nu - nu_c)).  That delay is the *phase* delay of the reference
solution: the non-dispersive path (troposphere, clocks) is the same number of seconds
in both bands, and the unwrapped phase measures it far more precisely than the group
delay of a 2-GHz window.  The table's rate (s/s) is the same in both bands for the
same reason; CASA turns it into a phase rate with the target table's nu_c, i.e. it is
scaled by R_c there.

Without wrap counting (``wrap_counting=False``: u = phi, the wrapped solution phase)
this is the CFPT analogue, R_k * phi, whose target phase jumps by 2*pi*eps_k at every
wrap of phi.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import SolutionIntervalError
from .read import WindowSolutions
from .wraps import PREDICT_RATES, PREDICT_SLOPE, TWO_PI, segment_starts, unwrap_solutions

#: the fraction of bridged residuals beyond pi/2 that says the phase moved by more than pi
#: between solutions (uniform residuals give 0.5; a tracked series almost none)
ITOH_FRACTION = 0.1
#: fewest steps of a series on which the Itoh check is made
ITOH_MIN_STEPS = 8


@dataclass(frozen=True)
class UnwrappedWindow:
    """One window's solutions with their wraps counted, in the first reference frame."""

    source: WindowSolutions
    unwrapped: np.ndarray     # (n_sol, n_ant, n_rec) float64: phase + offset + 2*pi*wraps
    wraps: np.ndarray         # (n_sol, n_ant, n_rec) int64
    offset: np.ndarray        # (n_sol, n_rec) float64 frame offset (reference antenna changes)
    residual: np.ndarray      # (n_sol, n_ant, n_rec) float64 bridged residual, NaN where none
    switch: np.ndarray        # (n_sol, n_rec) int8 reference antenna changes (wraps.BRIDGED...)
    new_segment: np.ndarray   # (n_sol,) bool: a scan or a gap starts


@dataclass(frozen=True)
class TargetWindow:
    """Transferred solutions for one target spectral window (one Fringe Jones row each)."""

    spw: int
    field: int
    centre_hz: float
    times: np.ndarray         # (n_sol,)
    scan: np.ndarray          # (n_sol,) int32
    phase: np.ndarray         # (n_sol, n_ant, n_rec) float64: R_c * u (unwrapped)
    delay_s: np.ndarray       # (n_sol, n_ant, n_rec) float64
    rate: np.ndarray          # (n_sol, n_ant, n_rec) float64 s/s
    valid: np.ndarray         # (n_sol, n_ant, n_rec) bool
    refant: np.ndarray        # (n_sol,) int32


def unwrap_window(window: WindowSolutions, max_gap: float, wrap_counting: bool = True,
                  has_rates: bool = True) -> UnwrappedWindow:
    """Count the wraps of every antenna and receptor of one window (or not: CFPT analogue).

    ``has_rates``: bridge with the table's rates (Fringe Jones), else with each series'
    own slope (G, T Jones).
    """
    n_sol, n_ant, n_rec = window.phase.shape
    starts = segment_starts(window.times, window.scan, max_gap)
    if not wrap_counting:
        nan = np.full(window.phase.shape, np.nan)
        return UnwrappedWindow(window, np.where(window.valid, window.phase, np.nan),
                               np.zeros(window.phase.shape, np.int64), np.zeros((n_sol, n_rec)),
                               nan, np.zeros((n_sol, n_rec), np.int8), starts)
    pieces = []
    for rec in range(n_rec):
        phase_rate = TWO_PI * window.ref_freq_hz * window.rate[:, :, rec]
        pieces.append(unwrap_solutions(np.ascontiguousarray(window.phase[:, :, rec]),
                                       np.ascontiguousarray(window.valid[:, :, rec]),
                                       window.times, np.ascontiguousarray(phase_rate),
                                       window.refant, starts,
                                       PREDICT_RATES if has_rates else PREDICT_SLOPE))
    return UnwrappedWindow(
        source=window,
        unwrapped=np.stack([p[0] for p in pieces], axis=2),
        wraps=np.stack([p[1] for p in pieces], axis=2),
        offset=np.stack([p[2] for p in pieces], axis=1),
        residual=np.stack([p[3] for p in pieces], axis=2),
        switch=np.stack([p[4] for p in pieces], axis=1),
        new_segment=starts)


def check_interval(unwrapped: UnwrappedWindow, antenna_names, path: str) -> None:
    """Refuse a table whose phase moves by more than pi between solutions (Itoh)."""
    w = unwrapped.source
    spacing = float(np.median(np.diff(w.times))) if w.times.size > 1 else 0.0
    for ant, name in enumerate(antenna_names):
        res = unwrapped.residual[:, ant, :]
        res = res[np.isfinite(res)]
        if res.size < ITOH_MIN_STEPS:
            continue
        beyond = float(np.mean(np.abs(res) > np.pi / 2))
        if beyond > ITOH_FRACTION:
            bridge = "the rates" if np.any(w.rate[:, ant]) else "the previous solutions' slope"
            raise SolutionIntervalError(
                f"reference table '{path}': the phase of station {name} (spectral window {w.spw}) "
                f"moves by more than pi between solutions {spacing:g} s apart ({100 * beyond:.0f}% "
                f"of its steps exceed pi/2 after the prediction from {bridge}): wrap counting is "
                "impossible; re-solve with a shorter solint (solutions a few seconds apart at 86 GHz)")


def series_rates(unwrapped: UnwrappedWindow) -> np.ndarray:
    """Rates (s/s) from the unwrapped phases: d u/dt / (2*pi*nu_ref), within each segment.

    For tables without rates (G, T).  CASA applycal (interp 'linear') carries a Fringe
    Jones phase between solutions with the rate (measured: 4-s G solutions transferred
    with zero rates gave a coherence of 0.74, with these rates 0.9992), so the target
    table needs them.  Central differences over the valid solutions of each segment;
    one-sided at its ends; 0 for a segment of one solution.
    """
    w = unwrapped.source
    rates = np.zeros(w.phase.shape)
    segment = np.cumsum(unwrapped.new_segment)
    for ant in range(w.phase.shape[1]):
        for rec in range(w.phase.shape[2]):
            ok = w.valid[:, ant, rec] & np.isfinite(unwrapped.unwrapped[:, ant, rec])
            for seg in np.unique(segment[ok]):
                idx = np.flatnonzero(ok & (segment == seg))
                if idx.size > 1:
                    rates[idx, ant, rec] = np.gradient(unwrapped.unwrapped[idx, ant, rec],
                                                       w.times[idx]) / (TWO_PI * w.ref_freq_hz)
    return rates


def transfer_window(unwrapped: UnwrappedWindow, spw: int, field: int, centre_hz: float,
                    has_rates: bool = True) -> TargetWindow:
    """The target window's phase at its centre, delay and rate from one unwrapped reference window.

    ``has_rates``: the reference table carries rates (Fringe Jones); otherwise they are
    derived from the unwrapped series (:func:`series_rates`).
    """
    w = unwrapped.source
    u = unwrapped.unwrapped
    valid = w.valid & np.isfinite(u)
    u0 = np.where(valid, u, 0.0)
    rate = w.rate if has_rates else series_rates(unwrapped)
    return TargetWindow(spw=int(spw), field=int(field), centre_hz=float(centre_hz), times=w.times,
                        scan=w.scan, phase=u0 * (centre_hz / w.ref_freq_hz),
                        delay_s=u0 / (TWO_PI * w.ref_freq_hz), rate=np.where(valid, rate, 0.0),
                        valid=valid, refant=w.refant)


def channel_phases(unwrapped: np.ndarray, ref_freq_hz: float, chan_freq_hz: np.ndarray) -> np.ndarray:
    """phase_k = (nu_k / nu_ref) * u for every channel: (..., n_chan) from u (...)."""
    return np.asarray(unwrapped)[..., None] * (np.asarray(chan_freq_hz) / ref_freq_hz)
