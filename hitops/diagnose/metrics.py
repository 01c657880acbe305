"""Coherence metrics per baseline and column: C(T), its curve over T, and tau_c.

* C(T) per (baseline, correlation) comes from the kernel
  :func:`hitops.kernels.coherence.segment_coherence`; the per-baseline value
  is the mean over the selected correlations that have data.
* tau_c, the paper's effective coherence time ("the expectation value of the
  averaging interval that produces an amplitude loss of e^-1"), is where the
  correlation-mean curve C(T) first falls to 1/e, interpolated linearly in
  log T between the two grid points around the crossing.  A curve that stays
  above 1/e up to the longest usable interval gives a lower bound
  (``>T_max``); one already below 1/e at the shortest interval gives an
  upper bound (``<T_min``).  Neither is replaced by a made-up number.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import InputError
from ..kernels.coherence import FIELDS, segment_coherence_dask

log = logging.getLogger("hitops.diagnose")

INV_E = math.exp(-1.0)


def parse_intervals(spec) -> np.ndarray:
    """Interval grid from ``1,2,5,10``, ``log:START:STOP:N`` or ``lin:START:STOP:N`` (s)."""
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        raise InputError("--intervals is empty; give e.g. log:1:3600:30 or 1,2,5,10,30")
    if not isinstance(spec, str):
        values = np.asarray(spec, dtype=np.float64).ravel()
    else:
        text = spec.strip().lower()
        if text.startswith(("log:", "lin:")):
            parts = text.split(":")
            try:
                start, stop, num = float(parts[1]), float(parts[2]), int(parts[3])
                if len(parts) != 4:
                    raise ValueError
            except (ValueError, IndexError):
                raise InputError(f"--intervals '{spec}': write {parts[0]}:START:STOP:N, "
                                 "e.g. log:1:3600:30") from None
            if num < 1 or not (start > 0 and stop >= start):
                raise InputError(f"--intervals '{spec}': need 0 < START <= STOP and N >= 1")
            values = (np.geomspace(start, stop, num) if text.startswith("log")
                      else np.linspace(start, stop, num))
        else:
            try:
                values = np.array([float(v) for v in text.split(",") if v.strip()])
            except ValueError:
                raise InputError(f"--intervals '{spec}': not a comma-separated list of "
                                 "seconds nor log:/lin:START:STOP:N") from None
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise InputError(f"--intervals '{spec}': every interval must be a positive number of "
                         "seconds")
    return np.unique(values)


def run_lengths(times: np.ndarray, scan: np.ndarray, dt: float) -> np.ndarray:
    """Longest scan run (s, including one sampling interval) on each baseline."""
    n_bl = scan.shape[0]
    longest = np.zeros(n_bl)
    for b in range(n_bl):
        present = np.flatnonzero(scan[b] >= 0)
        if present.size == 0:
            continue
        s = scan[b, present]
        breaks = np.flatnonzero(np.diff(s) != 0)
        starts = np.concatenate([[0], breaks + 1])
        ends = np.concatenate([breaks, [present.size - 1]])
        spans = times[present[ends]] - times[present[starts]] + dt
        longest[b] = spans.max()
    return longest


@dataclass
class CoherenceResult:
    """Coherence of every selected baseline, column and correlation."""

    columns: List[str]
    corr_names: List[str]
    intervals: np.ndarray           # (n_int,) grid of T (s), ascending
    interval: float                 # the single T of the coherence-factor metric
    k_interval: int                 # index of ``interval`` in ``intervals``
    c_mean: Dict[str, np.ndarray]   # column -> (n_bl, n_corr, n_int)
    c_std: Dict[str, np.ndarray]    # column -> (n_bl, n_corr, n_int)
    n_segments: Dict[str, np.ndarray]  # column -> (n_bl, n_corr, n_int)
    n_usable: Dict[str, np.ndarray]    # column -> (n_bl, n_corr)
    longest_run: np.ndarray         # (n_bl,) s

    def curve(self, column: str) -> np.ndarray:
        """Correlation-mean C(T) per baseline (n_bl, n_int); NaN where no correlation has data."""
        return nanmean_or_nan(self.c_mean[column], axis=1)

    def curve_err(self, column: str) -> np.ndarray:
        """Standard error of :meth:`curve` (between-segment scatter / sqrt(segments))."""
        std = self.c_std[column]
        nseg = self.n_segments[column]
        with np.errstate(invalid="ignore", divide="ignore"):
            se2 = np.where(nseg > 0, std ** 2 / np.maximum(nseg, 1), np.nan)
            n_ok = np.sum(np.isfinite(se2), axis=1)
            return np.where(n_ok > 0, np.sqrt(np.nansum(se2, axis=1)) / np.maximum(n_ok, 1),
                            np.nan)


def nanmean_or_nan(values: np.ndarray, axis: int) -> np.ndarray:
    finite = np.isfinite(values)
    count = finite.sum(axis=axis)
    total = np.where(finite, values, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def compute_coherence(vis_stack: np.ndarray, columns: List[str], flag: np.ndarray,
                      times: np.ndarray, scan: np.ndarray, dt: float, intervals: np.ndarray,
                      interval: float, min_fill: float = 0.5,
                      corr_names: Optional[List[str]] = None, bl_chunk: int = 4,
                      scheduler: str = "threads") -> CoherenceResult:
    """C(T) for every column over ``intervals`` plus ``interval``, in one dask compute.

    ``vis_stack`` is (n_bl, n_time, n_col, n_corr) with columns in the order
    of ``columns``; ``flag`` (n_bl, n_time, n_corr) applies to every column.
    """
    import dask
    import dask.array as da

    grid = np.union1d(np.asarray(intervals, dtype=np.float64), [float(interval)])
    k_interval = int(np.flatnonzero(np.isclose(grid, interval))[0])
    n_bl, n_time, n_col, n_corr = vis_stack.shape
    series = vis_stack.reshape(n_bl, n_time, n_col * n_corr)
    chunk = max(1, min(bl_chunk, n_bl))
    stacked = segment_coherence_dask(da.from_array(series, chunks=(chunk, -1, -1)),
                                     da.from_array(flag, chunks=(chunk, -1, -1)), times,
                                     da.from_array(scan, chunks=(chunk, -1)),
                                     grid, dt, min_fill)
    # schedulers as functions, so dask does not import distributed to look for a client
    import dask.local
    import dask.threaded
    get = {"threads": dask.threaded.get, "sync": dask.local.get_sync}.get(scheduler, scheduler)
    (arr,) = dask.compute(stacked, scheduler=get)
    arr = arr.reshape(n_bl, n_col, n_corr, grid.size, len(FIELDS))
    out = {name: {} for name in FIELDS}
    for i, col in enumerate(columns):
        out["c_mean"][col] = arr[:, i, :, :, 0]
        out["c_std"][col] = arr[:, i, :, :, 1]
        out["n_segments"][col] = arr[:, i, :, :, 2].astype(np.int64)
        out["n_usable"][col] = arr[:, i, :, 0, 3].astype(np.int64)
    return CoherenceResult(columns=list(columns), corr_names=list(corr_names or []),
                           intervals=grid, interval=float(interval), k_interval=k_interval,
                           c_mean=out["c_mean"], c_std=out["c_std"],
                           n_segments=out["n_segments"], n_usable=out["n_usable"],
                           longest_run=run_lengths(times, scan, dt))


def coherence_time(intervals: np.ndarray, curve: np.ndarray) -> Tuple[float, str]:
    """tau_c of one C(T) curve: (value, bound) with bound '=', '>' or '<'.

    '>' means C stays above 1/e up to the last finite grid point (value =
    that T, a lower bound); '<' means C is already at or below 1/e at the
    first finite grid point (value = that T, an upper bound).  A curve with
    no finite point gives (nan, '') and must be reported by the caller.
    """
    ok = np.isfinite(curve)
    if not ok.any():
        return math.nan, ""
    t = intervals[ok]
    c = curve[ok]
    below = np.flatnonzero(c <= INV_E)
    if below.size == 0:
        return float(t[-1]), ">"
    k = int(below[0])
    if k == 0:
        return float(t[0]), "<"
    # linear interpolation in log T between the bracketing grid points
    c0, c1 = c[k - 1], c[k]
    frac = (c0 - INV_E) / (c0 - c1)
    log_tau = math.log(t[k - 1]) + frac * (math.log(t[k]) - math.log(t[k - 1]))
    return float(math.exp(log_tau)), "="
