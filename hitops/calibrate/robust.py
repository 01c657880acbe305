"""Robust reference-band wrap tracking inside ``hitops calibrate`` (issue 6, part B).

The paper's tracker (``--tracker count``) compares consecutive samples and
runs inside the baseline-group tasks of :mod:`hitops.calibrate.transfer`,
carrying one sample across time chunks.  The robust trackers look further:

* ``smooth``  - :func:`hitops.kernels.tracking.track_wraps_smooth` per
  (baseline, correlation): smoothed unit phasor over a window sized from the
  per-sample SNR and the coherence time, gap bridging, jump detection;
* ``antenna`` - :func:`hitops.tracking.modes.track_antennas` per parallel-hand
  correlation: per-sample antenna phase solve, wraps tracked per antenna,
  baseline counts snapped to the antenna model, so n0 is per antenna and
  closure phases carry no 2 pi eps k.  Cross-hand correlations (RL, LR, XY,
  YX) have no antenna model here and use ``smooth``.

Both run here, in the driver (local threads; the kernels release the GIL), on the whole array of one time chunk *with
context*: the reference rows of ``context`` extra time samples on either
side are read too, the tracker runs on the extended chunk, and its counts
are aligned to the counts already written for the overlapping context
(:class:`History`).  The kernels' reach is bounded (smoothing +-h, bridged
gaps <= max_gap, jump windows, the SNR window), so with
``context >= context_samples(...)`` the output does not depend on the chunk
size (tested).  Across a gap longer than the context, which is a new,
unresolved segment anyway, the count continues from the last one.

Time axis: the kernels work on a regular grid, so within each scan the
union time axis of calibrate is mapped onto a grid of step dt (the median
time step); missing times are invalid samples, so gaps are visible.

Per-sample SNR (for the smoothing windows, docs/tracking.md): from SIGMA
(or WEIGHT = 1/SIGMA^2) when the reference set has informative values,
rho(t) = A / sigma, A estimated over the valid visibilities within
+-snr_window samples from the mean power, A^2 = <|V|^2> - 2 sigma^2, which
does not depend on how fast the phase moves inside the window; otherwise
from the data:
|<exp(i (phi_{t+1} - phi_t))>| = m^2, m the mean resultant length of one
noisy unit phasor, inverted through
:func:`hitops.tracking.theory.mean_resultant_length`.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ..errors import InputError, StationError

log = logging.getLogger("hitops.calibrate")

TRACKER_CHOICES = ("count", "smooth", "antenna")
JUMP_ACTIONS = ("segment", "flag")
TWO_PI = 2.0 * math.pi


def _wrap_pi(x):
    """Radians wrapped to [-pi, pi) (NaN stays NaN)."""
    return (x + math.pi) % TWO_PI - math.pi
#: smoothed-phasor mean resultant below which a sample is suspect (kernel default)
MIN_COHERENCE = 0.2
#: antenna tracks are smoothed over +-2 samples after a windowed solve (docs/tracking.md)
ANTENNA_TRACK_HALF_WINDOW = 2
#: segment keys are scan index * SEGMENT_KEY + segment id
SEGMENT_KEY = np.int64(1) << 32
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


def check_options(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                  jump_window, jump_action, solve_half_window) -> None:
    """Validate the tracking options (before anything is read or written)."""
    if tracker not in TRACKER_CHOICES:
        raise InputError(f"--tracker: unknown wrap tracker {tracker!r}; choose one of "
                         f"{', '.join(TRACKER_CHOICES)} (docs/tracking.md)")
    checks = [
        (half_window, "--half-window", lambda v: int(v) == v and v >= 0,
         "an integer >= 0 (0: per-sample windows from the SNR and --coherence-time)"),
        (coherence_time, "--coherence-time", lambda v: math.isfinite(v) and v > 0,
         "a positive number of seconds (reference-band coherence time, e.g. 20)"),
        (snr, "--snr", lambda v: math.isfinite(v) and v >= 0,
         "a number >= 0 (0: per-sample SNR from SIGMA/WEIGHT or the data)"),
        (max_gap, "--max-gap", lambda v: int(v) == v and v >= -1,
         "an integer >= 0 samples, or -1 for the default from --coherence-time"),
        (jump_threshold, "--jump-threshold", lambda v: math.isfinite(v) and (v == -1 or 0 <= v < 180),
         "degrees in (0, 180), 0 to switch jump detection off, or -1 for the default"),
        (jump_window, "--jump-window", lambda v: int(v) == v and v >= 0,
         "an integer >= 0 samples (0: the default from the SNR and --coherence-time)"),
        (solve_half_window, "--solve-half-window", lambda v: int(v) == v and v >= -1,
         "an integer >= 0 samples, or -1 for the default"),
    ]
    for value, name, ok, what in checks:
        try:
            good = ok(float(value))
        except (TypeError, ValueError):
            good = False
        if not good:
            raise InputError(f"{name} {value!r} must be {what}")
    if jump_action not in JUMP_ACTIONS:
        raise InputError(f"--jump-action {jump_action!r}: choose segment (start a new, reported "
                         "segment at each jump) or flag (flag the reference samples from each "
                         "jump to the end of its segment)")


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


def sigma_source(ref_ms: str) -> str:
    """'sigma' or 'weight' when that column of ``ref_ms`` holds informative values, else 'data'.

    CASA fills SIGMA and WEIGHT with 1 when nothing better is known; such
    columns say nothing about the SNR, and the SNR is then taken from the data.
    """
    from casacore import tables as pt

    with pt.table(ref_ms, ack=False) as t:
        names = set(t.colnames())
        for column, kind in (("SIGMA", "sigma"), ("WEIGHT", "weight")):
            if column not in names or t.nrows() == 0:
                continue
            values = t.getcol(column)
            if values.size and np.all(np.isfinite(values)) and np.all(values > 0) \
                    and not np.all(values == 1.0):
                return kind
    return "data"


@functools.lru_cache(maxsize=4096)
def _half_window_for(rho2: float, coherence_time: float, dt: float) -> int:
    from ..tracking.theory import recommended_half_window
    return int(recommended_half_window(rho2, coherence_time, dt))


def _two_digits(x: float) -> float:
    if not (x > 0 and math.isfinite(x)):
        return x
    e = math.floor(math.log10(x)) - 1
    return round(x / 10 ** e) * 10 ** e


def setup_tracking(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                   jump_window, jump_action, refant, solve_half_window, dt, antenna_names,
                   snr_from: str, elevation_scaling: bool = False) -> TrackingSetup:
    """Resolve the defaults of docs/tracking.md ("Recommended defaults for calibrate")."""
    from ..tracking import theory

    coherence_time = float(coherence_time)
    t_c_samples = coherence_time / dt
    cap = max(1, int((t_c_samples - 1) // 2))          # windows stay below t_c
    snr = float(snr)
    h_fixed = int(half_window)
    if h_fixed == 0 and snr > 0:
        h_fixed = _half_window_for(_two_digits(snr), coherence_time, dt)
    m_gap = int(max_gap) if int(max_gap) >= 0 else theory.recommended_max_gap(coherence_time, dt)
    jump_snr = snr if snr > 0 else NOMINAL_JUMP_SNR
    rec_window, rec_threshold = theory.recommended_jump_params(jump_snr, coherence_time, dt)
    if float(jump_threshold) == -1:
        threshold = rec_threshold
    else:
        threshold = math.radians(float(jump_threshold))
    window = int(jump_window) if int(jump_window) > 0 else rec_window
    solve_h = int(solve_half_window)
    if solve_h < 0 and h_fixed > 0:
        solve_h = min(h_fixed, cap)
    # solve_h < 0 left: a solve window per time from the antennas' combined SNR
    h_max = h_fixed if h_fixed > 0 else cap
    if tracker == "antenna":
        h_max = max(h_max, (solve_h if solve_h >= 0 else cap) + ANTENNA_TRACK_HALF_WINDOW)
    snr_window = 10 if snr_from in ("sigma", "weight") else 30
    # reach of the kernels: smoothing and rate bases (2h+1), bridged gaps, jump windows
    # (statistic and peak search), the SNR window; doubled for the solve window
    reach_window = max(window, 2 * max(solve_h, 0) + 1) if tracker == "antenna" else window
    context = 2 * (2 * h_max + 1) + (m_gap + 1) + 2 * reach_window + snr_window + 16
    if tracker == "smooth" and threshold == 0:
        log.info("jump detection is off (threshold 0: at SNR %.3g and t_c %.3g s noise and "
                 "turbulence would hide jumps of pi)", jump_snr, coherence_time)
    return TrackingSetup(tracker=tracker, dt=float(dt), coherence_time=coherence_time, snr=snr,
                         snr_source="fixed" if snr > 0 else snr_from, half_window=h_fixed,
                         max_half_window=cap, max_gap=m_gap, jump_window=window,
                         jump_threshold=float(threshold), jump_action=jump_action,
                         refants=parse_refants(refant, antenna_names), solve_half_window=solve_h,
                         snr_window=snr_window, context=int(context),
                         elevation_scaling=bool(elevation_scaling))


def station_sin_elevation(ms: str, times: np.ndarray) -> Optional[np.ndarray]:
    """sin(elevation) of the phase centre at each station of ``ms``, (n_ant, n_time); None
    when the geometry is missing (zero positions).

    The J2000 direction is rotated into ITRF by the Earth rotation angle only
    (precession and nutation, ~0.3 deg since 2000, are ignored): good enough
    for the sin(el)^(3/5) scaling of the coherence time.
    """
    from ..io import read as msio
    from ..simulate.geometry import earth_rotation_angle, geodetic_up

    positions = np.asarray(msio.read_subtable(ms, "ANTENNA", ["POSITION"])["POSITION"], float)
    phase_dir = np.asarray(msio.read_subtable(ms, "FIELD", ["PHASE_DIR"])["PHASE_DIR"], float)
    radius = np.linalg.norm(positions, axis=1) if positions.size else np.zeros(0)
    # stations on the Earth's surface (6.35-6.39 Mm from the centre), else no usable geometry
    if radius.size == 0 or phase_dir.size == 0 or np.any((radius < 6.33e6) | (radius > 6.40e6)):
        return None
    ra, dec = phase_dir.reshape(-1, 2)[0]
    era = earth_rotation_angle(times)
    hour = era - ra        # Greenwich hour angle; ITRF source direction below
    src = np.stack([np.cos(dec) * np.cos(hour), -np.cos(dec) * np.sin(hour),
                    np.full(times.shape, np.sin(dec))], axis=0)
    return geodetic_up(positions) @ src


def grid_positions(times: np.ndarray, scan_of_time: np.ndarray):
    """(position on a regular grid of each union time, dt); positions count from 0 per run.

    dt is the median step within scans; times off that grid by more than 1 per
    cent of a step make the union index itself the position (logged).
    """
    steps = np.diff(times)
    same_scan = np.diff(scan_of_time) == 0
    inside = steps[same_scan & (steps > 0)]
    dt = float(np.median(inside)) if inside.size else 1.0
    pos = np.round((times - times[0]) / dt)
    if times.size and np.max(np.abs((times - times[0]) / dt - pos)) > 0.01:
        log.warning("times are not on a regular %.4g s grid; the robust trackers treat each "
                    "time as one step (gaps in time are then not seen as gaps)", dt)
        return np.arange(times.size, dtype=np.int64), dt
    return pos.astype(np.int64), dt


# ----------------------------------------------------------------------------- gathering

def gather_grid(rows, vis, ok, swapped, corr_map, sigma=None):
    """(n_bl, n_corr, n_t) complex128 visibilities (0 where invalid), validity, sigma.

    Same validity rule as :func:`hitops.kernels.fpt.gather_phase` (unflagged,
    finite, non-zero); swapped rows are conjugated.
    """
    n_bl, n_t = rows.shape
    n_corr = corr_map.shape[1]
    out = np.zeros((n_bl, n_corr, n_t), np.complex128)
    good = np.zeros((n_bl, n_corr, n_t), bool)
    sig = np.full((n_bl, n_corr, n_t), np.nan) if sigma is not None else None
    has = rows >= 0
    r = rows[has]
    sw = swapped[r].astype(bool)
    for c in range(n_corr):
        ci = np.where(sw, corr_map[1, c], corr_map[0, c])
        usable = ci >= 0
        v = np.zeros(r.size, np.complex128)
        o = np.zeros(r.size, bool)
        v[usable] = vis[r[usable], ci[usable]]
        o[usable] = ok[r[usable], ci[usable]]
        v = np.where(sw, np.conj(v), v)
        o &= np.isfinite(v.real) & np.isfinite(v.imag) & (v != 0)
        out[:, c][has] = np.where(o, v, 0)
        good[:, c][has] = o
        if sigma is not None:
            s = np.full(r.size, np.nan)
            s[usable] = sigma[r[usable], ci[usable]]
            sig[:, c][has] = s
    return out, good, sig


def _running(values: np.ndarray, k: int) -> np.ndarray:
    """Sum over +-k samples along the last axis."""
    n = values.shape[-1]
    csum = np.concatenate([np.zeros(values.shape[:-1] + (1,), values.dtype),
                           np.cumsum(values, axis=-1)], axis=-1)
    hi = np.minimum(np.arange(n) + k + 1, n)
    lo = np.maximum(np.arange(n) - k, 0)
    return csum[..., hi] - csum[..., lo]


@functools.lru_cache(maxsize=1)
def _resultant_table():
    from ..tracking.theory import mean_resultant_length
    rho = np.concatenate([np.linspace(0.02, 1, 50), np.linspace(1.02, 12, 200)])
    m = np.array([mean_resultant_length(r, 1001) for r in rho])
    return rho, m


def per_sample_snr(vis: np.ndarray, valid: np.ndarray, sigma: Optional[np.ndarray],
                   window: int) -> np.ndarray:
    """Per-sample SNR estimate of each regular series (n, L); NaN where unknown."""
    v = np.where(valid, vis, 0)
    n = _running(valid.astype(np.float64), window)
    with np.errstate(invalid="ignore", divide="ignore"):
        if sigma is not None:
            # incoherent: <|V|^2> = A^2 + 2 sigma^2 whatever the phase does inside the
            # window (a coherent |<V>| would fall where turbulence is fast, at low
            # elevation, and ask for longer windows exactly where they must be short)
            s2 = _running(np.where(valid, sigma, 0.0) ** 2, window) / n
            power = _running(np.abs(v) ** 2, window) / n
            rho = np.sqrt(np.clip(power - 2.0 * s2, 0, None) / s2)
        else:
            unit = np.where(valid, v / np.where(valid, np.abs(v), 1), 0)
            pair = unit[:, 1:] * np.conj(unit[:, :-1])
            pair = np.concatenate([pair, np.zeros((pair.shape[0], 1), pair.dtype)], axis=1)
            pair_ok = np.concatenate([valid[:, 1:] & valid[:, :-1],
                                      np.zeros((valid.shape[0], 1), bool)], axis=1)
            m2 = np.abs(_running(pair, window)) / _running(pair_ok.astype(np.float64), window)
            grid_rho, grid_m = _resultant_table()
            rho = np.interp(np.sqrt(np.clip(m2, 0, 1)), grid_m, grid_rho)
    return np.where(valid, rho, np.nan)


def _regular(values, pos, length):
    """Values at union-axis samples placed on a regular grid of ``length`` (NaN elsewhere)."""
    out = np.full(values.shape[:-1] + (length,), np.nan)
    out[..., pos] = values
    return out


def _round2(x: np.ndarray) -> np.ndarray:
    digits = np.floor(np.log10(x)) - 1
    return np.round(x / 10.0 ** digits) * 10.0 ** digits


def half_windows_from_snr(rho: np.ndarray, setup: TrackingSetup, coherence_time=None) -> np.ndarray:
    """Per-sample half-windows from per-sample SNR and (local) coherence time.

    :func:`hitops.tracking.theory.recommended_half_window`, evaluated once per
    distinct pair after rounding both to 2 significant digits (cached).
    ``coherence_time`` broadcasts against ``rho``; default the setup's.
    """
    t_c = np.broadcast_to(setup.coherence_time if coherence_time is None else coherence_time,
                          rho.shape)
    out = np.ones(rho.shape, np.int64)
    ok = np.isfinite(rho) & (rho > 0) & np.isfinite(t_c) & (t_c > 0)
    if ok.any():
        keys = np.stack([_round2(rho[ok]), _round2(np.maximum(t_c[ok], setup.dt))], axis=1)
        unique, inverse = np.unique(keys, axis=0, return_inverse=True)
        values = np.array([_half_window_for(float(r), float(t), setup.dt) for r, t in unique],
                          np.int64)
        out[ok] = values[inverse.ravel()]
    # no signal left (SNR estimate 0): the widest window the local t_c allows
    low = np.isfinite(rho) & (rho <= 0) & np.isfinite(t_c)
    out[low] = np.clip(((t_c[low] / setup.dt - 1) // 2).astype(np.int64), 1, setup.max_half_window)
    return out


# ----------------------------------------------------------------------------- state

@dataclass
class History:
    """Aligned results of the last ``context`` time samples, and per-series state."""

    context: int
    n_bl: int
    n_corr: int
    n_ant: int
    t_start: int = 0                      # time index of column 0 of the arrays below
    counts: np.ndarray = None             # (n_bl, n_corr, ctx) int64
    valid: np.ndarray = None              # (n_bl, n_corr, ctx) bool
    seg: np.ndarray = None                # (n_bl, n_corr, ctx) int64
    ant_unw: np.ndarray = None            # (n_corr, n_ant, ctx) float64 unwrapped antenna phases
    ant_counts: np.ndarray = None         # (n_corr, n_ant, ctx) int64
    ant_seg: np.ndarray = None            # (n_corr, n_ant, ctx) int64
    ant_valid: np.ndarray = None          # (n_corr, n_ant, ctx) bool
    last_scan: np.ndarray = None          # (n_bl, n_corr) scan of the last valid sample (-1)
    last_count: np.ndarray = None
    last_seg: np.ndarray = None
    last_suspect: np.ndarray = None
    ant_last_scan: np.ndarray = None      # (n_corr, n_ant)
    ant_last_count: np.ndarray = None
    ant_last_seg: np.ndarray = None
    flag_seg: np.ndarray = None           # (n_bl, n_corr, 2): (scan, segment) flagged after a jump
    ant_flag_seg: np.ndarray = None       # (n_corr, n_ant, 2)

    @classmethod
    def empty(cls, context, n_bl, n_corr, n_ant):
        h = cls(context, n_bl, n_corr, n_ant)
        h.counts = np.zeros((n_bl, n_corr, 0), np.int64)
        h.valid = np.zeros((n_bl, n_corr, 0), bool)
        h.seg = np.zeros((n_bl, n_corr, 0), np.int64)
        h.ant_unw = np.zeros((n_corr, n_ant, 0))
        h.ant_counts = np.zeros((n_corr, n_ant, 0), np.int64)
        h.ant_seg = np.zeros((n_corr, n_ant, 0), np.int64)
        h.ant_valid = np.zeros((n_corr, n_ant, 0), bool)
        h.last_scan = np.full((n_bl, n_corr), -1, np.int64)
        h.last_count = np.zeros((n_bl, n_corr), np.int64)
        h.last_seg = np.full((n_bl, n_corr), -1, np.int64)
        h.last_suspect = np.zeros((n_bl, n_corr), bool)
        h.ant_last_scan = np.full((n_corr, n_ant), -1, np.int64)
        h.ant_last_count = np.zeros((n_corr, n_ant), np.int64)
        h.ant_last_seg = np.full((n_corr, n_ant), -1, np.int64)
        h.flag_seg = np.full((n_bl, n_corr, 2), -1, np.int64)
        h.ant_flag_seg = np.full((n_corr, n_ant, 2), -1, np.int64)
        return h


@dataclass
class Stats:
    """Confidence numbers per series (baseline x correlation) and per antenna x correlation."""

    n_bl: int
    n_corr: int
    n_ant: int
    per_series: Dict[str, np.ndarray] = field(default_factory=dict)
    per_antenna: Dict[str, np.ndarray] = field(default_factory=dict)
    jumps: List[tuple] = field(default_factory=list)        # (bl, corr, time index, rad)
    ant_jumps: List[tuple] = field(default_factory=list)    # (corr, ant, time index, rad)
    frame_breaks: int = 0

    KEYS = ("suspected_slips", "suspect_samples", "bridged_gaps", "segments",
            "long_gap_segments", "jumps", "jump_flagged", "wrap_events", "unmodelled")

    def __post_init__(self):
        for k in self.KEYS:
            self.per_series[k] = np.zeros((self.n_bl, self.n_corr), np.int64)
            self.per_antenna[k] = np.zeros((self.n_corr, self.n_ant), np.int64)


# ----------------------------------------------------------------------------- tracking

def _per_sample_model(out):
    """Unwrapped per-sample antenna phases on the tracked antennas' lobes; (phase, valid).

    ``out``: one scan run of :meth:`ReferenceTracker._antenna`, aligned.  The
    per-sample solution and the tracked one may sit in frames rotated by a common
    angle (reference-antenna changes): that angle (circular mean over the antennas)
    is removed before each antenna takes the 2 pi lobe nearest its tracked phase.
    A common angle cancels in every baseline A_p - A_q.
    """
    tracked = out["ant_phase"] - TWO_PI * out["ant_counts"]
    ok = out["raw_valid"] & out["ant_valid"] & np.isfinite(out["raw_phase"])
    raw = np.where(ok, out["raw_phase"], 0.0)
    frame = np.angle(np.sum(np.where(ok, np.exp(1j * (tracked - raw)), 0), axis=0))
    raw = raw + frame[None, :]
    model = raw + TWO_PI * np.round((np.where(ok, tracked, 0.0) - raw) / TWO_PI)
    return model, ok


def _smooth_series(args):
    """track_wraps_smooth on one regular series (a thread-pool job; the kernel is nogil)."""
    from ..kernels.tracking import track_wraps_smooth
    phase, valid, hw, setup = args
    kwargs = dict(max_gap=setup.max_gap, jump_window=setup.jump_window,
                  jump_threshold=setup.jump_threshold, min_coherence=MIN_COHERENCE)
    if hw is None:
        return track_wraps_smooth(phase, valid, half_window=setup.half_window, **kwargs)
    # per-sample windows; the scalar half_window sets the base of the gap-bridging rates
    return track_wraps_smooth(phase, valid, half_window=setup.max_half_window, half_windows=hw,
                              **kwargs)


class ReferenceTracker:
    """Runs the robust tracker chunk by chunk (see the module doc)."""

    def __init__(self, setup: TrackingSetup, match, corr_names: List[str], n_ant: int,
                 antenna_names: List[str], workers: int = 0, sin_elevation=None):
        self.setup = setup
        self.match = match
        self.n_bl = match.n_bl
        self.n_corr = len(corr_names)
        self.n_ant = n_ant
        self.corr_names = corr_names
        self.antenna_names = antenna_names
        self.parallel = [len(c) == 2 and c[0] == c[1] for c in corr_names]
        self.pos, _ = grid_positions(match.times, match.scan_of_time)
        # local coherence time per station and time: t_c sin(el)^(3/5) (the phase
        # variance of a thin screen grows with airmass), when the geometry is known
        self.station_tc = None
        if setup.elevation_scaling and sin_elevation is not None:
            from ..tracking.theory import local_coherence_time
            self.station_tc = local_coherence_time(setup.coherence_time, sin_elevation)
        self.hist = History.empty(setup.context, self.n_bl, self.n_corr, n_ant)
        self.stats = Stats(self.n_bl, self.n_corr, n_ant)
        # antenna mode: each station's unwrapped reference phase per correlation and union
        # time, as transferred (the gains of a calibration table); NaN where unsolved
        self.antenna_phase = (np.full((n_ant, self.n_corr, match.n_time), np.nan)
                              if setup.tracker == "antenna" else None)
        # ... and its tracking segment (aligned across chunks; -1 where none)
        self.antenna_segment = (np.full((n_ant, self.n_corr, match.n_time), -1, np.int64)
                                if setup.tracker == "antenna" else None)
        self.workers = workers or (os.cpu_count() or 1)
        if setup.tracker == "antenna" and not any(self.parallel):
            log.warning("antenna tracking needs parallel-hand correlations (RR, LL, XX, YY); "
                        "%s are tracked per baseline with the smooth tracker",
                        ",".join(corr_names))

    # -- the extended range of a chunk
    def extended(self, t0: int, t1: int):
        ctx = self.setup.context
        return max(0, t0 - ctx), min(self.match.n_time, t1 + ctx)

    def track(self, t_lo: int, t0: int, t1: int, t_hi: int, vis, valid, sigma):
        """Counts (n_bl, n_corr, t1-t0) and reference samples to exclude (jump flagging).

        vis/valid/sigma: (n_bl, n_corr, t_hi - t_lo) gridded reference samples.
        """
        setup = self.setup
        scan = self.match.scan_of_time[t_lo:t_hi]
        n_ext = t_hi - t_lo
        counts = np.zeros((self.n_bl, self.n_corr, n_ext), np.int64)
        seg = np.full((self.n_bl, self.n_corr, n_ext), -1, np.int64)
        suspect = np.zeros((self.n_bl, self.n_corr, n_ext), bool)
        bridged = np.zeros_like(suspect)
        jump = np.zeros((self.n_bl, self.n_corr, n_ext))
        unmodelled = np.zeros_like(suspect)
        ant = {}
        from .transfer import scan_segments   # imports the numba kernels (not at start-up)
        for a, b, _ in scan_segments(scan):
            pos = self.pos[t_lo + a:t_lo + b] - self.pos[t_lo + a]
            length = int(pos[-1]) + 1
            reg_vis = np.zeros((self.n_bl, self.n_corr, length), np.complex128)
            reg_valid = np.zeros((self.n_bl, self.n_corr, length), bool)
            reg_vis[..., pos] = vis[..., a:b]
            reg_valid[..., pos] = valid[..., a:b]
            reg_phase = np.where(reg_valid, np.angle(reg_vis), np.nan)
            antenna_corrs = [c for c in range(self.n_corr)
                             if setup.tracker == "antenna" and self.parallel[c]]
            smooth_corrs = [c for c in range(self.n_corr) if c not in antenna_corrs]
            if smooth_corrs:
                hw = None
                if setup.half_window == 0:
                    reg_sigma = None
                    if sigma is not None:
                        reg_sigma = np.full((self.n_bl, self.n_corr, length), np.nan)
                        reg_sigma[..., pos] = sigma[..., a:b]
                    hw = np.ones((self.n_bl, self.n_corr, length), np.int64)
                    tc_bl = None
                    if self.station_tc is not None:
                        # baseline: the worse station's local t_c (docs/tracking.md)
                        tc = self.station_tc[:, t_lo + a:t_lo + b]
                        tc_bl = _regular(np.minimum(tc[self.match.ant1], tc[self.match.ant2]),
                                         pos, length)
                    for c in smooth_corrs:
                        rho = per_sample_snr(reg_vis[:, c], reg_valid[:, c],
                                             None if reg_sigma is None else reg_sigma[:, c],
                                             setup.snr_window)
                        hw[:, c] = half_windows_from_snr(rho, setup, tc_bl)
                jobs = [(np.ascontiguousarray(reg_phase[bl, c]),
                         np.ascontiguousarray(reg_valid[bl, c]),
                         None if hw is None else np.ascontiguousarray(hw[bl, c]), setup)
                        for bl in range(self.n_bl) for c in smooth_corrs]
                keys = [(bl, c) for bl in range(self.n_bl) for c in smooth_corrs]
                if self.workers > 1 and len(jobs) > 1:
                    with ThreadPoolExecutor(self.workers) as pool:
                        results = list(pool.map(_smooth_series, jobs))
                else:
                    results = [_smooth_series(j) for j in jobs]
                for (bl, c), res in zip(keys, results):
                    counts[bl, c, a:b] = res[0][pos]
                    seg[bl, c, a:b] = res[1][pos]
                    suspect[bl, c, a:b] = res[2][pos]
                    bridged[bl, c, a:b] = res[3][pos]
                    jump[bl, c, a:b] = res[4][pos]
            for c in antenna_corrs:
                solve_h = setup.solve_half_window
                if solve_h < 0:
                    tc_t = None
                    if self.station_tc is not None:
                        # the antennas present: the lowest one's local t_c sets the window
                        tc_t = _regular(self.station_tc[:, t_lo + a:t_lo + b].min(axis=0), pos, length)
                    solve_h = self._solve_windows(
                        reg_vis[:, c], reg_valid[:, c],
                        None if sigma is None else _regular(sigma[:, c, a:b], pos, length), tc_t)
                out = self._antenna(reg_vis[:, c], reg_valid[:, c], pos, solve_h)
                counts[:, c, a:b], seg[:, c, a:b] = out["counts"], out["seg"]
                suspect[:, c, a:b], bridged[:, c, a:b] = out["suspect"], out["bridged"]
                unmodelled[:, c, a:b] = out["unmodelled"]
                ant.setdefault(c, []).append((a, b, out))
        seg = np.where(valid, seg, -1)
        counts, seg, ant = self._align(t_lo, t0, t1, scan, valid, counts, seg, ant)
        # antenna mode: each baseline's reference phase becomes its antenna model, the
        # unwrapped difference of its two stations' tracked phases; R times it is what the
        # target band receives, so the target's closure phases are kept (docs/tracking.md)
        model = np.full((self.n_bl, self.n_corr, n_ext), np.nan)
        p_ant, q_ant = self.match.ant1, self.match.ant2
        for c, runs in ant.items():
            for a, b, out in runs:
                # a baseline's segment is the pair of its antennas' (aligned) segments
                sp, sq = out["ant_seg"][p_ant], out["ant_seg"][q_ant]
                seg[:, c, a:b] = np.where(valid[:, c, a:b] & (sp >= 0) & (sq >= 0),
                                          sp * 1_000_003 + sq, -1)
                ant_model, ant_ok = _per_sample_model(out)
                # keep this chunk's own times (its context belongs to the neighbours)
                lo, hi = max(a, t0 - t_lo), min(b, t1 - t_lo)
                if hi > lo:
                    self.antenna_phase[:, c, t_lo + lo:t_lo + hi] = np.where(
                        ant_ok, ant_model, np.nan)[:, lo - a:hi - a]
                    self.antenna_segment[:, c, t_lo + lo:t_lo + hi] = out["ant_seg"][:, lo - a:hi - a]
                both = ant_ok[p_ant] & ant_ok[q_ant]
                bl_model = np.where(both, ant_model[p_ant] - ant_model[q_ant], np.nan)
                model[:, c, a:b] = bl_model
                # the count that goes with the model's wrapped phase (unwrapped = phase - 2 pi n)
                with np.errstate(invalid="ignore"):
                    model_counts = np.round((_wrap_pi(bl_model) - bl_model) / TWO_PI)
                counts[:, c, a:b] = np.where(both, model_counts, out["counts"]).astype(np.int64)
        exclude = self._jump_flags(t_lo, t0, t1, scan, valid, seg, jump, ant)
        self._collect(t_lo, t0, t1, scan, valid, counts, seg, suspect, bridged, jump,
                      unmodelled, ant, exclude)
        self._remember(t_lo, t0, t1, scan, valid, counts, seg, ant)
        i0, i1 = t0 - t_lo, t1 - t_lo
        # segment keys (scan index << 32 | aligned segment id): the per-segment offset step
        keys = np.where(seg >= 0, scan.astype(np.int64)[None, None, :] * SEGMENT_KEY + seg, -1)
        return counts[..., i0:i1], exclude[..., i0:i1], keys[..., i0:i1], model[..., i0:i1]

    def _solve_windows(self, vis, valid, sigma, coherence_time=None):
        """Per-time solve half-windows from the antennas' combined per-sample SNR.

        An antenna solution combines its baselines: its SNR is about
        sqrt(sum of rho_pq^2) over its baselines (stations.antenna_snr); each
        baseline feeds two antennas, so the typical antenna has
        sqrt(2 sum_b rho_b^2 / n_present).
        """
        rho = per_sample_snr(vis, valid, sigma, self.setup.snr_window)
        power = np.nansum(np.where(valid, rho, 0.0) ** 2, axis=0)
        present = np.zeros((self.n_ant, valid.shape[1]), bool)
        present[self.match.ant1] |= valid
        present[self.match.ant2] |= valid
        n_present = present.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            rho_ant = np.sqrt(2.0 * power / n_present)
        return half_windows_from_snr(np.where(n_present > 0, rho_ant, np.nan), self.setup,
                                     coherence_time)

    def _antenna(self, vis, valid, pos, solve_half_window):
        """Antenna mode on one regular scan run of one correlation; results at ``pos``."""
        from ..tracking.modes import track_antennas

        setup = self.setup
        fixed = np.ndim(solve_half_window) == 0
        res = track_antennas(vis, valid, self.match.ant1, self.match.ant2, self.n_ant,
                             refants=setup.refants, antenna_tracker="smooth",
                             solve_half_window=solve_half_window,
                             half_window=ANTENNA_TRACK_HALF_WINDOW, max_gap=setup.max_gap,
                             # a windowed solve spreads a jump over 2 s + 1 samples: the
                             # jump statistic must compare windows at least that long
                             jump_window=(max(setup.jump_window, 2 * int(solve_half_window) + 1)
                                          if fixed else setup.jump_window),
                             jump_threshold=setup.jump_threshold,
                             min_coherence=MIN_COHERENCE)
        ant_res = res.extra["antenna"]
        self.stats.frame_breaks += int(res.extra["frame_break"][pos].sum())
        # the phases transferred in antenna mode are solved per sample: the windowed solve
        # above chooses the lobes, but its smoothing error would enter the target band
        from ..kernels.antenna import solve_antenna_phases
        if np.any(np.asarray(solve_half_window) > 0):
            raw_phase, raw_valid = solve_antenna_phases(
                np.ascontiguousarray(vis), np.ascontiguousarray(valid), self.match.ant1,
                self.match.ant2, self.n_ant, np.asarray(setup.refants, np.int64))[:2]
        else:
            raw_phase, raw_valid = res.extra["ant_phase"], res.extra["ant_valid"]
        return {"counts": res.counts[:, pos], "seg": res.segment[:, pos],
                "suspect": res.suspect[:, pos], "bridged": res.bridged[:, pos],
                "unmodelled": res.extra["unmodelled"][:, pos],
                "ant_phase": res.extra["ant_phase"][:, pos], "ant_valid": res.extra["ant_valid"][:, pos],
                "ant_counts": ant_res.counts[:, pos], "ant_seg": ant_res.segment[:, pos],
                "ant_suspect": ant_res.suspect[:, pos], "ant_bridged": ant_res.bridged[:, pos],
                "ant_jump": ant_res.jump[:, pos], "bl_phase": np.angle(vis[:, pos]),
                "raw_phase": raw_phase[:, pos], "raw_valid": raw_valid[:, pos],
                "bl_valid": valid[:, pos]}

    # -- alignment with what earlier chunks wrote
    def _align(self, t_lo, t0, t1, scan, valid, counts, seg, ant):
        from ..kernels.antenna import baseline_counts_from_antennas

        h = self.hist
        i0 = t0 - t_lo
        if i0 == 0 or h.counts.shape[-1] == 0:
            return counts, seg, ant
        cont = scan[i0] == scan[i0 - 1] if i0 < scan.size else False
        if not cont:
            return counts, seg, ant
        run_a = i0
        while run_a > 0 and scan[run_a - 1] == scan[i0]:
            run_a -= 1
        run_b = i0
        while run_b < scan.size and scan[run_b] == scan[i0]:
            run_b += 1
        # history columns of the context [run_a, i0)
        hcol = np.arange(run_a, i0) + t_lo - h.t_start
        okcol = (hcol >= 0) & (hcol < h.counts.shape[-1])
        cols = np.arange(run_a, i0)[okcol]
        hcol = hcol[okcol]
        this_scan = int(scan[i0])
        antenna_corrs = set(ant)
        for c in range(self.n_corr):
            if c in antenna_corrs:
                continue
            for bl in range(self.n_bl):
                both = valid[bl, c, cols] & h.valid[bl, c, hcol]
                if both.any():
                    j = np.flatnonzero(both)[-1]
                    off = h.counts[bl, c, hcol[j]] - counts[bl, c, cols[j]]
                    soff = h.seg[bl, c, hcol[j]] - seg[bl, c, cols[j]]
                elif h.last_scan[bl, c] == this_scan:
                    # gap longer than the context: a new segment that continues the count
                    later = np.flatnonzero(valid[bl, c, i0:run_b])
                    if not later.size:
                        continue
                    k = i0 + later[0]
                    off = h.last_count[bl, c] - counts[bl, c, k]
                    soff = h.last_seg[bl, c] + 1 - seg[bl, c, k]
                else:
                    continue
                counts[bl, c, run_a:run_b] += off
                seg[bl, c, run_a:run_b] = np.where(seg[bl, c, run_a:run_b] >= 0,
                                                   seg[bl, c, run_a:run_b] + soff, -1)
        for c in antenna_corrs:
            for a, b, out in ant[c]:
                if not (a <= i0 < b):
                    continue
                sl = slice(run_a - a, i0 - a)
                new_unw = out["ant_phase"] - TWO_PI * out["ant_counts"]
                offs = np.zeros(self.n_ant, np.int64)
                soffs = np.zeros(self.n_ant, np.int64)
                diffs = {}
                for p in range(self.n_ant):
                    both = out["ant_valid"][p, sl] & h.ant_valid[c, p, hcol]
                    if both.any():
                        j = np.flatnonzero(both)[-1]
                        diffs[p] = (new_unw[p, sl][j] - h.ant_unw[c, p, hcol[j]],
                                    h.ant_seg[c, p, hcol[j]] - out["ant_seg"][p, sl][j])
                if diffs:
                    # common frame rotation between the two solves (same for all antennas)
                    frame = math.atan2(sum(math.sin(d) for d, _ in diffs.values()),
                                       sum(math.cos(d) for d, _ in diffs.values()))
                    for p, (d, s) in diffs.items():
                        offs[p] = int(round((d - frame) / TWO_PI))
                        soffs[p] = s
                for p in range(self.n_ant):
                    if p not in diffs and h.ant_last_scan[c, p] == this_scan:
                        later = np.flatnonzero(out["ant_valid"][p, i0 - a:])
                        if later.size:
                            k = i0 - a + later[0]
                            offs[p] = h.ant_last_count[c, p] - out["ant_counts"][p, k]
                            soffs[p] = h.ant_last_seg[c, p] + 1 - out["ant_seg"][p, k]
                out["ant_counts"] = out["ant_counts"] + offs[:, None]
                out["ant_seg"] = np.where(out["ant_seg"] >= 0, out["ant_seg"] + soffs[:, None], -1)
                bl_counts, _ = baseline_counts_from_antennas(
                    np.ascontiguousarray(out["bl_phase"]), np.ascontiguousarray(out["bl_valid"]),
                    self.match.ant1, self.match.ant2, np.ascontiguousarray(out["ant_phase"]),
                    np.ascontiguousarray(out["ant_valid"]), np.ascontiguousarray(out["ant_counts"]))
                out["counts"] = bl_counts
                counts[:, c, a:b] = bl_counts
        return counts, seg, ant

    def _jump_flags(self, t_lo, t0, t1, scan, valid, seg, jump, ant):
        """Reference samples excluded by --jump-action flag (from a jump to its segment's end)."""
        exclude = np.zeros(valid.shape, bool)
        if self.setup.jump_action != "flag":
            return exclude
        h = self.hist
        i0, i1 = t0 - t_lo, t1 - t_lo
        def flag_series(ok, jumps, sc, sg, state):
            """Samples of [jump, end of its segment), continuing ``state`` = (scan, segment)."""
            out = np.zeros(ok.size, bool)
            starts = np.flatnonzero(ok & (jumps != 0))
            if state[0] < 0 and not starts.size:
                return out, state
            if state[0] >= 0:
                out |= ok & (sc == state[0]) & (sg == state[1])
            for j in starts:
                state = np.array([sc[j], sg[j]])
                out[j:] |= ok[j:] & (sc[j:] == state[0]) & (sg[j:] == state[1])
            return out, state

        sc = scan[i0:i1]
        for bl in range(self.n_bl):
            for c in range(self.n_corr):
                if c in ant:
                    continue
                exclude[bl, c, i0:i1], h.flag_seg[bl, c] = flag_series(
                    valid[bl, c, i0:i1], jump[bl, c, i0:i1], sc, seg[bl, c, i0:i1],
                    h.flag_seg[bl, c])
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                bad = np.zeros((self.n_ant, hi - lo), bool)
                for p in range(self.n_ant):
                    k = slice(lo - a, hi - a)
                    bad[p], h.ant_flag_seg[c, p] = flag_series(
                        out["ant_valid"][p, k], out["ant_jump"][p, k], scan[lo:hi],
                        out["ant_seg"][p, k], h.ant_flag_seg[c, p])
                exclude[:, c, lo:hi] = (bad[self.match.ant1] | bad[self.match.ant2]) & valid[:, c, lo:hi]
        return exclude

    def _collect(self, t_lo, t0, t1, scan, valid, counts, seg, suspect, bridged, jump,
                 unmodelled, ant, exclude):
        """Accumulate the confidence numbers of the samples in [t0, t1)."""
        h = self.hist
        st = self.stats.per_series
        i0, i1 = t0 - t_lo, t1 - t_lo
        for bl in range(self.n_bl):
            for c in range(self.n_corr):
                idx = i0 + np.flatnonzero(valid[bl, c, i0:i1])
                if not idx.size:
                    continue
                sc = scan[idx]
                prev_scan = np.concatenate([[h.last_scan[bl, c]], sc[:-1]])
                prev_count = np.concatenate([[h.last_count[bl, c]], counts[bl, c, idx[:-1]]])
                prev_seg = np.concatenate([[h.last_seg[bl, c]], seg[bl, c, idx[:-1]]])
                prev_sus = np.concatenate([[h.last_suspect[bl, c]], suspect[bl, c, idx[:-1]]])
                same = sc == prev_scan
                sus = suspect[bl, c, idx] | unmodelled[bl, c, idx]
                st["suspect_samples"][bl, c] += int(sus.sum())
                st["suspected_slips"][bl, c] += int((sus & ~(prev_sus & same)).sum())
                st["bridged_gaps"][bl, c] += int(bridged[bl, c, idx].sum())
                st["unmodelled"][bl, c] += int(unmodelled[bl, c, idx].sum())
                starts = ~same | (seg[bl, c, idx] != prev_seg)
                st["segments"][bl, c] += int(starts.sum())
                is_jump = jump[bl, c, idx] != 0
                st["long_gap_segments"][bl, c] += int((starts & same & ~is_jump).sum())
                st["jumps"][bl, c] += int(is_jump.sum())
                for i in idx[is_jump]:
                    self.stats.jumps.append((bl, c, t_lo + int(i), float(jump[bl, c, i])))
                st["jump_flagged"][bl, c] += int(exclude[bl, c, idx].sum())
                st["wrap_events"][bl, c] += int(np.abs(counts[bl, c, idx] - prev_count)[same].sum())
                h.last_scan[bl, c] = sc[-1]
                h.last_count[bl, c] = counts[bl, c, idx[-1]]
                h.last_seg[bl, c] = seg[bl, c, idx[-1]]
                h.last_suspect[bl, c] = suspect[bl, c, idx[-1]]
        sa = self.stats.per_antenna
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                for p in range(self.n_ant):
                    k = np.flatnonzero(out["ant_valid"][p, lo - a:hi - a]) + lo - a
                    if not k.size:
                        continue
                    sc = scan[k + a]
                    prev_scan = np.concatenate([[h.ant_last_scan[c, p]], sc[:-1]])
                    prev_seg = np.concatenate([[h.ant_last_seg[c, p]], out["ant_seg"][p, k[:-1]]])
                    prev_count = np.concatenate([[h.ant_last_count[c, p]],
                                                 out["ant_counts"][p, k[:-1]]])
                    same = sc == prev_scan
                    sus = out["ant_suspect"][p, k]
                    prev_sus = np.concatenate([[False], sus[:-1]])
                    sa["suspect_samples"][c, p] += int(sus.sum())
                    sa["suspected_slips"][c, p] += int((sus & ~prev_sus).sum())
                    sa["bridged_gaps"][c, p] += int(out["ant_bridged"][p, k].sum())
                    starts = ~same | (out["ant_seg"][p, k] != prev_seg)
                    sa["segments"][c, p] += int(starts.sum())
                    is_jump = out["ant_jump"][p, k] != 0
                    sa["long_gap_segments"][c, p] += int((starts & same & ~is_jump).sum())
                    sa["jumps"][c, p] += int(is_jump.sum())
                    for kk in k[is_jump]:
                        self.stats.ant_jumps.append((c, p, t_lo + a + int(kk),
                                                     float(out["ant_jump"][p, kk])))
                    sa["wrap_events"][c, p] += int(
                        np.abs(out["ant_counts"][p, k] - prev_count)[same].sum())
                    h.ant_last_scan[c, p] = sc[-1]
                    h.ant_last_count[c, p] = out["ant_counts"][p, k[-1]]
                    h.ant_last_seg[c, p] = out["ant_seg"][p, k[-1]]

    def _remember(self, t_lo, t0, t1, scan, valid, counts, seg, ant):
        """Keep the aligned results of the last ``context`` samples up to t1."""
        h = self.hist
        ctx = h.context
        i0, i1 = t0 - t_lo, t1 - t_lo
        ant_unw = np.zeros((self.n_corr, self.n_ant, i1 - i0))
        ant_counts = np.zeros((self.n_corr, self.n_ant, i1 - i0), np.int64)
        ant_seg = np.full((self.n_corr, self.n_ant, i1 - i0), -1, np.int64)
        ant_valid = np.zeros((self.n_corr, self.n_ant, i1 - i0), bool)
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                src = slice(lo - a, hi - a)
                dst = slice(lo - i0, hi - i0)
                ant_unw[c, :, dst] = out["ant_phase"][:, src] - TWO_PI * out["ant_counts"][:, src]
                ant_counts[c, :, dst] = out["ant_counts"][:, src]
                ant_seg[c, :, dst] = out["ant_seg"][:, src]
                ant_valid[c, :, dst] = out["ant_valid"][:, src]
        if h.t_start + h.counts.shape[-1] != t0:     # not contiguous: start afresh
            h.counts = h.counts[..., :0]
            h.valid, h.seg = h.valid[..., :0], h.seg[..., :0]
            h.ant_unw, h.ant_counts = h.ant_unw[..., :0], h.ant_counts[..., :0]
            h.ant_seg, h.ant_valid = h.ant_seg[..., :0], h.ant_valid[..., :0]
            h.t_start = t0
        total = h.counts.shape[-1] + (t1 - t0)
        drop = max(0, total - ctx)
        h.counts = np.concatenate([h.counts, counts[..., i0:i1]], axis=-1)[..., drop:]
        h.valid = np.concatenate([h.valid, valid[..., i0:i1]], axis=-1)[..., drop:]
        h.seg = np.concatenate([h.seg, seg[..., i0:i1]], axis=-1)[..., drop:]
        h.ant_unw = np.concatenate([h.ant_unw, ant_unw], axis=-1)[..., drop:]
        h.ant_counts = np.concatenate([h.ant_counts, ant_counts], axis=-1)[..., drop:]
        h.ant_seg = np.concatenate([h.ant_seg, ant_seg], axis=-1)[..., drop:]
        h.ant_valid = np.concatenate([h.ant_valid, ant_valid], axis=-1)[..., drop:]
        h.t_start = h.t_start + drop

    # -- reporting
    def report(self, times: np.ndarray) -> dict:
        """Per-baseline (and per-antenna) confidence numbers for the JSON report."""
        st = self.stats
        t0 = float(times[0]) if times.size else 0.0
        baselines = []
        for bl, name in enumerate(self.match.baseline_names):
            entry = {"baseline": name}
            for k in Stats.KEYS:
                entry[k] = int(st.per_series[k][bl].sum())
            entry["per_correlation"] = {
                cn: {k: int(st.per_series[k][bl, c]) for k in Stats.KEYS}
                for c, cn in enumerate(self.corr_names)}
            entry["jump_list"] = [
                {"correlation": self.corr_names[c], "time": float(times[t]),
                 "time_from_start_s": float(times[t] - t0), "size_deg": math.degrees(size)}
                for b, c, t, size in st.jumps if b == bl]
            baselines.append(entry)
        out = {"setup": self.setup.as_dict(), "baselines": baselines}
        if self.setup.tracker == "antenna":
            antennas = []
            for p, name in enumerate(self.antenna_names):
                if not any(st.per_antenna["segments"][c, p] for c in range(self.n_corr)):
                    continue
                entry = {"antenna": name}
                for k in Stats.KEYS:
                    if k in ("unmodelled", "jump_flagged"):
                        continue
                    entry[k] = int(st.per_antenna[k][:, p].sum())
                entry["jump_list"] = [
                    {"correlation": self.corr_names[c], "time": float(times[t]),
                     "time_from_start_s": float(times[t] - t0), "size_deg": math.degrees(size)}
                    for c, q, t, size in st.ant_jumps if q == p]
                antennas.append(entry)
            out["antennas"] = antennas
            out["frame_breaks"] = st.frame_breaks
        return out


def segment_offset_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid):
    """Sums of exp(i (Phi_ref - Phi_out)) per (baseline, correlation, segment key).

    The per-segment form of the paper's n0 step (``fpt.offset_sums`` works per
    scan): keys (n_bl, n_corr, n_time) from :meth:`ReferenceTracker.track`,
    phasor/calibrated (n_bl, n_time, n_corr), the phases (n_bl, n_corr, n_time);
    Phi_ref is the offset reference's or the model's phase (``--offset-model``).
    Returns (index (m, 3) int64 rows of (baseline, correlation, key), sorted,
    sums complex128 (m,), counts int64 (m,)).  One numba pass over runs of equal
    key (:func:`hitops.calibrate.lattice.segment_run_sums`).
    """
    from .lattice import segment_run_sums
    return segment_run_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid)


def apply_segment_offsets(counts, keys, offsets: Dict[tuple, int]):
    """Counts with k added in every (baseline, correlation, segment) of ``offsets``.

    Adding k to the wrap count of a segment adds 2 pi eps k to its PWC output
    (and R 2 pi k = 2 pi eps k mod 2 pi to CWU): the per-segment n0 step.  One
    sorted look-up per series, whatever the number of segments.
    """
    if not offsets:
        return counts
    per_series: Dict[tuple, list] = {}
    for (b, c, key), k in offsets.items():
        if k:
            per_series.setdefault((int(b), int(c)), []).append((int(key), int(k)))
    if not per_series:
        return counts
    out = counts.copy()
    for (b, c), items in per_series.items():
        items.sort()
        table = np.array([key for key, _ in items], np.int64)
        values = np.array([k for _, k in items], np.int64)
        series = keys[b, c]
        pos = np.minimum(np.searchsorted(table, series), table.size - 1)
        out[b, c] += np.where(table[pos] == series, values[pos], 0)
    return out
