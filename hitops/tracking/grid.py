"""The grid the trackers work on, and the reference samples gathered onto it.

A tracker runs on a :class:`TrackGrid`: calibrate's matched baselines and union
times, and the tracking scans (:class:`ScanAxis`) no wrap is counted across.
Both are built whole by calibrate's plan, then only read.

The kernels count in samples of a *regular* grid: within each scan the union
time axis of calibrate is mapped onto a grid of step dt (the median time
step), and missing times become invalid samples, so a gap is a gap the
tracker can see.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from ..errors import InputError
from ..io.layout import GridShape

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class ScanSplit:
    """A tracking scan started inside a SCAN_NUMBER at a long time gap."""

    scan_number: int                # the SCAN_NUMBER that was split
    time: float                     # first time after the gap (MJD seconds)
    gap_s: float                    # length of the gap (seconds)


@dataclass(frozen=True)
class ScanAxis:
    """The tracking scans of a time axis: wraps are counted within a scan, never across.

    Built by :meth:`hitops.calibrate.chunks.GroupMatch.check` from SCAN_NUMBER,
    then by :meth:`split_at_gaps` (a new axis; this one is left as it is).
    """

    scan_numbers: np.ndarray        # (n_scan,) SCAN_NUMBER of each tracking scan
    scan_of_time: np.ndarray        # (n_time,) int64 index in scan_numbers of each time

    @property
    def n_scan(self) -> int:
        return self.scan_numbers.size

    def split_at_gaps(self, times: np.ndarray,
                      min_gap_s: float) -> Tuple["ScanAxis", List[ScanSplit]]:
        """(the axis with a new tracking scan at every time gap longer than ``min_gap_s``,
        the splits).

        Wrap counting must not run across a stretch with no data at all, whatever
        SCAN_NUMBER says (a UVFITS round trip through CASA can merge every scan
        into one).  ``scan_numbers`` of the new axis repeats a SCAN_NUMBER where
        one was split.
        """
        scan_of_time = self.scan_of_time
        if times.size < 2:
            return self, []
        gaps = np.diff(times)
        cut = np.flatnonzero((gaps > min_gap_s) & (scan_of_time[1:] == scan_of_time[:-1])) + 1
        if cut.size == 0:
            return self, []
        starts = np.zeros(times.size, dtype=bool)
        starts[0] = True
        starts[1:] = scan_of_time[1:] != scan_of_time[:-1]
        starts[cut] = True
        splits = [ScanSplit(int(self.scan_numbers[scan_of_time[i]]), float(times[i]),
                            float(gaps[i - 1])) for i in cut]
        return ScanAxis(self.scan_numbers[scan_of_time[starts]], np.cumsum(starts) - 1), splits


@dataclass(frozen=True)
class TrackGrid(GridShape):
    """What a tracker reads of calibrate's plan: the (baseline, time) grid and its scans."""

    times: np.ndarray               # (n_time,) union times (MJD seconds)
    ant1: np.ndarray                # (n_bl,) target-set antenna index of each baseline
    ant2: np.ndarray
    baseline_names: List[str]       # "ANT1-ANT2" station codes of each baseline
    scans: ScanAxis


def grid_positions(times: np.ndarray, scan_of_time: Optional[np.ndarray] = None,
                   dt: Optional[float] = None, tolerance: float = 0.01, strict: bool = False):
    """(position on a regular grid of each distinct time, dt); positions count from 0.

    dt (when not given) is the median positive step within scans (``scan_of_time``
    None: one scan).  Times off that grid by more than ``tolerance`` of a step
    raise InputError when ``strict``; otherwise the union index itself becomes the
    position (logged: gaps in time are then not seen as gaps).
    """
    times = np.asarray(times, dtype=np.float64)
    if dt is None:
        steps = np.diff(times)
        same_scan = (np.ones(steps.size, bool) if scan_of_time is None
                     else np.diff(scan_of_time) == 0)
        inside = steps[same_scan & (steps > 0)]
        dt = float(np.median(inside)) if inside.size else 1.0
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt}")
    if times.size == 0:
        return np.zeros(0, np.int64), float(dt)
    pos = np.round((times - times[0]) / dt)
    off = np.max(np.abs((times - times[0]) / dt - pos))
    if off > tolerance:
        if strict:
            raise InputError(f"times are not on a regular {dt} s grid (off by {off * dt:.3g} s); "
                             "pass the integration time explicitly or average to a common grid")
        log.warning("times are not on a regular %.4g s grid; the robust trackers treat each "
                    "time as one step (gaps in time are then not seen as gaps)", dt)
        return np.arange(times.size, dtype=np.int64), float(dt)
    return pos.astype(np.int64), float(dt)


def on_grid(values: np.ndarray, pos: np.ndarray, length: int, fill=np.nan) -> np.ndarray:
    """Values at samples ``pos`` of a regular grid of ``length`` (``fill`` elsewhere)."""
    dtype = np.result_type(values, np.asarray(fill))
    out = np.full(values.shape[:-1] + (length,), fill, dtype=dtype)
    out[..., pos] = values
    return out


def gather_grid(rows, vis, ok, swapped, corr_map, sigma=None):
    """(n_bl, n_corr, n_t) complex128 visibilities (0 where invalid), validity, sigma.

    ``rows`` (n_bl, n_t) row index or -1; ``corr_map`` (2, n_corr) the input
    correlation for unswapped / swapped rows.  Same validity rule as
    :func:`hitops.kernels.fpt.gather_phase` (unflagged, finite, non-zero);
    swapped rows are conjugated.  The trackers need the complex values (antenna
    solves, SNR), which is why this is not gather_phase.
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
