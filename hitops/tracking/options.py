"""Tracking options of ``hitops calibrate``: numeric checks and the resolved setup.

The choices (``--tracker``, ``--jump-action``) are enforced by the schema
(hitops/schemas/calibrate.yml); :func:`check_options` checks only what a
schema choice cannot say (integers, ranges), before anything is read.
:func:`setup_tracking` then resolves the defaults of docs/tracking.md
("Recommended defaults for calibrate") from the time step, the coherence time
and the SNR, including the chunk context the kernels' reach needs.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from ..errors import InputError, StationError
from . import theory
from ..io import tables

log = logging.getLogger("hitops.calibrate")

#: smoothed-phasor mean resultant below which a sample is suspect (kernel default)
MIN_COHERENCE = 0.2
#: antenna tracks are smoothed over +-2 samples after a windowed solve (docs/tracking.md)
ANTENNA_TRACK_HALF_WINDOW = 2
#: nominal per-sample SNR for the jump threshold when --snr is not given (conservative:
#: a lower SNR gives a higher threshold, hence fewer false jumps)
NOMINAL_JUMP_SNR = 2.0


@dataclass
class TrackingSetup:
    """Resolved tracking parameters (samples of the regular grid unless stated)."""

    tracker: str
    dt: float
    coherence_time: float          # s, reference band
    snr: float                     # fixed per-sample SNR, 0: per sample
    snr_source: str                # 'fixed', 'sigma', 'weight', 'data'
    half_window: int               # fixed smoothing half-window, 0: per sample
    max_half_window: int           # cap of per-sample half-windows
    max_gap: int
    jump_window: int
    jump_threshold: float          # rad, 0: off
    jump_action: str
    refants: np.ndarray            # int64 target antenna indices, in order of preference
    solve_half_window: int         # antenna mode
    snr_window: int
    context: int
    elevation_scaling: bool = False
    sin_elevation: Optional[np.ndarray] = None   # (n_ant, n_time) when scaling

    def as_dict(self) -> dict:
        return {"tracker": self.tracker, "dt_s": self.dt, "coherence_time_s": self.coherence_time,
                "snr": self.snr, "snr_source": self.snr_source,
                "elevation_scaling": self.elevation_scaling,
                "half_window": self.half_window if self.half_window > 0 else "per-sample",
                "max_half_window": self.max_half_window, "max_gap": self.max_gap,
                "jump_window": self.jump_window,
                "jump_threshold_deg": math.degrees(self.jump_threshold),
                "jump_action": self.jump_action, "refants": self.refants.tolist(),
                "solve_half_window": (self.solve_half_window if self.solve_half_window >= 0
                                      else "per-time"),
                "snr_window": self.snr_window,
                "context_samples": self.context}


def _integer(v, low):
    return int(v) == v and v >= low


#: (option, check on its float value, what it must be)
_CHECKS = {
    "half_window": ("--half-window", lambda v: _integer(v, 0),
                    "an integer >= 0 (0: per-sample windows from the SNR and --coherence-time)"),
    "coherence_time": ("--coherence-time", lambda v: math.isfinite(v) and v > 0,
                       "a positive number of seconds (reference-band coherence time, e.g. 20)"),
    "snr": ("--snr", lambda v: math.isfinite(v) and v >= 0,
            "a number >= 0 (0: per-sample SNR from SIGMA/WEIGHT or the data)"),
    "max_gap": ("--max-gap", lambda v: _integer(v, -1),
                "an integer >= 0 samples, or -1 for the default from --coherence-time"),
    "jump_threshold": ("--jump-threshold",
                       lambda v: math.isfinite(v) and (v == -1 or 0 <= v < 180),
                       "degrees in (0, 180), 0 to switch jump detection off, or -1 for the default"),
    "jump_window": ("--jump-window", lambda v: _integer(v, 0),
                    "an integer >= 0 samples (0: the default from the SNR and --coherence-time)"),
    "solve_half_window": ("--solve-half-window", lambda v: _integer(v, -1),
                          "an integer >= 0 samples, or -1 for the default"),
}


def check_options(tracking) -> None:
    """Raise InputError for a tracking option out of range: ``tracking`` is calibrate's
    tracking section (hitops/schemas/calibrate.yml), or anything with the names of
    :data:`_CHECKS` as attributes."""
    for key, (name, ok, what) in _CHECKS.items():
        value = getattr(tracking, key)
        try:
            good = ok(float(value))
        except (TypeError, ValueError):
            good = False
        if not good:
            raise InputError(f"{name} {value!r} must be {what}")


def parse_refants(refant, antenna_names: List[str]) -> np.ndarray:
    """Target antenna indices of the comma-separated station names (or indices) in ``refant``."""
    if not refant:
        return np.zeros(0, np.int64)
    out = []
    for item in str(refant).split(","):
        item = item.strip()
        if not item:
            continue
        if item in antenna_names:
            out.append(antenna_names.index(item))
        elif item.isdigit() and int(item) < len(antenna_names):
            out.append(int(item))
        else:
            raise StationError(f"--refant: station {item!r} is not in the target set's ANTENNA "
                               f"table ({', '.join(antenna_names)})")
    return np.asarray(out, np.int64)


#: rows of SIGMA/WEIGHT read to decide whether they are informative
SIGMA_SAMPLE_ROWS = 100_000


def sigma_source(ref_ms: str) -> str:
    """'sigma' or 'weight' when that column of ``ref_ms`` holds informative values, else 'data'.

    CASA fills SIGMA and WEIGHT with 1 when nothing better is known; such
    columns say nothing about the SNR, and the SNR is then taken from the data.
    At most :data:`SIGMA_SAMPLE_ROWS` rows, spread evenly over the table, are
    looked at, so the check stays within the run's memory budget.
    """
    from ..io.msv4.store import is_processing_set
    if is_processing_set(ref_ms):   # a processing set's WEIGHT (hitops/io/msv4/columns.py)
        from ..io.msv4.group_rows import weight_source
        return weight_source(ref_ms, SIGMA_SAMPLE_ROWS)
    with tables.main_table(ref_ms) as t:
        names = set(t.colnames())
        n_rows = t.nrows()
        step = max(1, -(-n_rows // SIGMA_SAMPLE_ROWS))
        for column, kind in (("SIGMA", "sigma"), ("WEIGHT", "weight")):
            if column not in names or n_rows == 0:
                continue
            values = t.getcol(column, 0, -(-n_rows // step), step)
            if values.size and np.all(np.isfinite(values)) and np.all(values > 0) \
                    and not np.all(values == 1.0):
                return kind
    return "data"


@functools.lru_cache(maxsize=4096)
def half_window_for(rho: float, coherence_time: float, dt: float) -> int:
    """:func:`hitops.tracking.theory.recommended_half_window`, cached (windows ask it often)."""
    return int(theory.recommended_half_window(rho, coherence_time, dt))


def two_digits(x):
    """x rounded to 2 significant digits (positive values; others unchanged).

    The windows are looked up per distinct rounded (SNR, t_c): a few hundred
    evaluations of the theory instead of one per sample.
    """
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        digits = np.floor(np.log10(x)) - 1
        rounded = np.round(x / 10.0 ** digits) * 10.0 ** digits
    return np.where((x > 0) & np.isfinite(x), rounded, x)


def _context(tracker, h_max, m_gap, window, solve_h, snr_window) -> int:
    """Samples of reference read either side of a chunk: the kernels' reach.

    Smoothing and rate bases (2h+1), bridged gaps, jump windows (statistic and
    peak search), the SNR window; the solve window doubles in antenna mode.
    """
    reach_window = max(window, 2 * max(solve_h, 0) + 1) if tracker == "antenna" else window
    return 2 * (2 * h_max + 1) + (m_gap + 1) + 2 * reach_window + snr_window + 16


def setup_tracking(tracking, dt: float, antenna_names, snr_from: str,
                   sin_elevation=None) -> TrackingSetup:
    """Resolve the defaults of docs/tracking.md ("Recommended defaults for calibrate").

    ``tracking``: calibrate's tracking section (``tracker``, ``half_window``,
    ``coherence_time``, ``snr``, ``max_gap``, ``jump_threshold``, ``jump_window``,
    ``jump_action``, ``refant``, ``solve_half_window``); ``dt`` the grid's time step (s).
    ``sin_elevation`` (n_ant, n_time) or None: with it the coherence time is
    scaled per station as sin(el)^(3/5) (``elevation_scaling``).
    """
    tracker, jump_action = tracking.tracker, tracking.jump_action
    half_window, snr, max_gap = tracking.half_window, tracking.snr, tracking.max_gap
    jump_threshold, jump_window = tracking.jump_threshold, tracking.jump_window
    solve_half_window = tracking.solve_half_window
    coherence_time = float(tracking.coherence_time)
    cap = max(1, int((coherence_time / dt - 1) // 2))          # windows stay below t_c
    snr = float(snr)
    h_fixed = int(half_window)
    if h_fixed == 0 and snr > 0:
        h_fixed = half_window_for(float(two_digits(snr)), coherence_time, dt)
    m_gap = int(max_gap) if int(max_gap) >= 0 else theory.recommended_max_gap(coherence_time, dt)
    jump_snr = snr if snr > 0 else NOMINAL_JUMP_SNR
    rec_window, rec_threshold = theory.recommended_jump_params(jump_snr, coherence_time, dt)
    threshold = (rec_threshold if float(jump_threshold) == -1
                 else math.radians(float(jump_threshold)))
    window = int(jump_window) if int(jump_window) > 0 else rec_window
    solve_h = int(solve_half_window)
    if solve_h < 0 and h_fixed > 0:
        solve_h = min(h_fixed, cap)
    # solve_h < 0 left: a solve window per time from the antennas' combined SNR
    h_max = h_fixed if h_fixed > 0 else cap
    if tracker == "antenna":
        h_max = max(h_max, (solve_h if solve_h >= 0 else cap) + ANTENNA_TRACK_HALF_WINDOW)
    snr_window = 10 if snr_from in ("sigma", "weight") else 30
    if tracker == "smooth" and threshold == 0:
        log.info("jump detection is off (threshold 0: at SNR %.3g and t_c %.3g s noise and "
                 "turbulence would hide jumps of pi)", jump_snr, coherence_time)
    return TrackingSetup(tracker=tracker, dt=float(dt), coherence_time=coherence_time, snr=snr,
                         snr_source="fixed" if snr > 0 else snr_from, half_window=h_fixed,
                         max_half_window=cap, max_gap=m_gap, jump_window=window,
                         jump_threshold=float(threshold), jump_action=jump_action,
                         refants=parse_refants(tracking.refant, antenna_names), solve_half_window=solve_h,
                         snr_window=snr_window,
                         context=int(_context(tracker, h_max, m_gap, window, solve_h, snr_window)),
                         elevation_scaling=sin_elevation is not None, sin_elevation=sin_elevation)
