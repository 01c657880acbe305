"""Coherence factor over consecutive time segments, per baseline and correlation.

The paper's coherence factor (fpt-arbitrary-ratios.tex, eq. "coherence_factor";
Thompson, Moran & Swenson 2017, sec. 9.3; Zhao et al. 2025) is

    C(T) = | (1/T) integral_0^T exp(i phi(t)) dt |,

the amplitude kept when a unit-amplitude phasor is averaged coherently over
an interval T.  On sampled, flagged data it becomes, for one segment,

    C_seg = | sum_j exp(i phi_j) | / n_seg,      j over the usable samples,

and C(T) of a whole track is the mean of C_seg over segments.

Rules (documented in docs/diagnose.md):

* segments are consecutive intervals [t0 + kT, t0 + (k+1)T) where t0 is the
  first row of the baseline in each scan, so segments never straddle a scan
  boundary and are aligned identically for every column compared;
* a sample is usable when it has a row, is not flagged, and its visibility
  is finite and non-zero (the phase of 0 is undefined);
* a segment whose usable samples number less than ``min_fill * T / dt``
  (dt the sampling interval) is left out: the trailing partial segment of a
  scan and heavily flagged segments would otherwise bias C upwards (a
  one-sample segment always has C = 1);
* the mean over segments is weighted by each segment's number of usable
  samples, which for unflagged regular data is the plain mean.

Each baseline's unit phasors are summed cumulatively once; every segment of
every interval is then one difference of two cumulative sums, so a grid of
intervals costs one pass over time per interval, not one per sample.

:func:`segment_coherence` is the pure kernel; :func:`segment_coherence_dask`
maps it over chunks of baselines.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: fields of the last axis of :func:`segment_coherence_stacked`
FIELDS = ("c_mean", "c_std", "n_segments", "n_usable")


@numba.njit(cache=True, nogil=True)
def segment_coherence(vis, flag, times, scan, intervals, dt, min_fill):
    """Coherence factor of every (baseline, series) for every interval.

    Parameters
    ----------
    vis : complex (n_bl, n_time, n_series)
        Visibilities on a (baseline, time) grid; only their phase is used.
        A series is one correlation of one column; several columns may be
        stacked along this axis (column-major: series = column * n_flag + corr)
        so the segment walk, which depends only on times and scans, is shared.
    flag : bool (n_bl, n_time, n_flag)
        True where a sample must be left out; series ``s`` uses
        ``flag[..., s % n_flag]`` (n_flag must divide n_series).
    times : float64 (n_time,)
        Ascending sample times (s).
    scan : int (n_bl, n_time)
        Scan number of each cell, negative where the cell has no row.
    intervals : float64 (n_int,)
        Segment lengths T (s), each > 0.
    dt : float
        Sampling interval (s): a full segment holds T/dt samples.
    min_fill : float
        Segments with fewer than ``min_fill * T / dt`` usable samples are left out.

    Returns
    -------
    c_mean : float64 (n_bl, n_series, n_int)
        Sample-weighted mean of C over the kept segments; NaN where none was kept.
    c_std : float64 (n_bl, n_series, n_int)
        Sample-weighted standard deviation of C between kept segments (NaN where none).
    n_segments : int64 (n_bl, n_series, n_int)
        Number of kept segments.
    n_usable : int64 (n_bl, n_series)
        Number of usable samples.
    """
    n_bl, n_time, n_series = vis.shape
    n_int = intervals.shape[0]
    c_mean = np.full((n_bl, n_series, n_int), np.nan)
    c_std = np.full((n_bl, n_series, n_int), np.nan)
    n_segments = np.zeros((n_bl, n_series, n_int), dtype=np.int64)
    n_usable = np.zeros((n_bl, n_series), dtype=np.int64)
    # a sample exactly on a segment boundary belongs to the later segment,
    # whatever the rounding of TIME (MJD seconds keep ~1e-6 s)
    nudge = 1e-3 * dt
    for b in range(n_bl):
        csum, ccount = _cumulative_phasors(vis, flag, scan, b)
        for s in range(n_series):
            n_usable[b, s] = ccount[n_time, s]
        for k in range(n_int):
            interval = intervals[k]
            need = max(min_fill * interval / dt, 1.0)
            w_sum, w_sq, w_n, k_seg = _interval_segments(csum, ccount, times, scan[b], interval,
                                                         need, nudge)
            for s in range(n_series):
                n_segments[b, s, k] = k_seg[s]
                if k_seg[s] > 0:
                    mean = w_sum[s] / w_n[s]
                    c_mean[b, s, k] = mean
                    var = w_sq[s] / w_n[s] - mean * mean
                    c_std[b, s, k] = math.sqrt(var) if var > 0.0 else 0.0
    return c_mean, c_std, n_segments, n_usable


@numba.njit(cache=True, nogil=True)
def _cumulative_phasors(vis, flag, scan, b):
    """Cumulative unit-phasor sums and usable counts of baseline ``b``, (n_time + 1,
    n_series) each: index t holds the sum over samples [0, t)."""
    _, n_time, n_series = vis.shape
    n_flag = flag.shape[2]
    csum = np.zeros((n_time + 1, n_series), dtype=np.complex128)
    ccount = np.zeros((n_time + 1, n_series), dtype=np.int64)
    for t in range(n_time):
        present = scan[b, t] >= 0
        for s in range(n_series):
            v = vis[b, t, s]
            amp = abs(v)
            if present and not flag[b, t, s % n_flag] and amp > 0.0 and math.isfinite(amp):
                csum[t + 1, s] = csum[t, s] + v / amp
                ccount[t + 1, s] = ccount[t, s] + 1
            else:
                csum[t + 1, s] = csum[t, s]
                ccount[t + 1, s] = ccount[t, s]
    return csum, ccount


@numba.njit(cache=True, nogil=True)
def _interval_segments(csum, ccount, times, scan_b, interval, need, nudge):
    """One baseline's segments of length ``interval``: per series the sums of n * C,
    n * C^2 and n over the kept segments (n >= ``need`` usable samples), and their number."""
    n_time = times.shape[0]
    n_series = csum.shape[1]
    w_sum = np.zeros(n_series)
    w_sq = np.zeros(n_series)
    w_n = np.zeros(n_series)
    k_seg = np.zeros(n_series, dtype=np.int64)
    seg_start = -1      # time index where the open segment starts
    run_scan = -1       # scan of the current run
    run_t0 = 0.0        # start time of the current run
    seg_end = 0.0       # end time of the open segment
    for t in range(n_time + 1):
        close = False
        start_run = False
        if t == n_time:
            close = seg_start >= 0
        else:
            sc = scan_b[t]
            if sc < 0:
                continue
            if sc != run_scan or seg_start < 0:
                close = seg_start >= 0
                start_run = True
            elif times[t] - run_t0 + nudge >= seg_end:
                close = True
        if close:
            for s in range(n_series):
                n = ccount[t, s] - ccount[seg_start, s]
                if n > 0 and n >= need:
                    dz = csum[t, s] - csum[seg_start, s]
                    coh = math.sqrt(dz.real * dz.real + dz.imag * dz.imag) / n
                    w_sum[s] += n * coh
                    w_sq[s] += n * coh * coh
                    w_n[s] += n
                    k_seg[s] += 1
            seg_start = -1
        if t == n_time:
            break
        if start_run:
            run_scan = scan_b[t]
            run_t0 = times[t]
            seg_end = interval
            seg_start = t
        elif close:
            # the segment this sample falls in (gaps may skip several)
            seg_id = math.floor((times[t] - run_t0 + nudge) / interval)
            seg_end = (seg_id + 1) * interval
            seg_start = t
    return w_sum, w_sq, w_n, k_seg


@numba.njit(cache=True, nogil=True)
def segment_coherence_stacked(vis, flag, times, scan, intervals, dt, min_fill):
    """:func:`segment_coherence` packed into one float64 (n_bl, n_series, n_int, 4) array.

    Last axis as :data:`FIELDS`; ``n_usable`` is repeated along the interval axis.
    One array per block keeps the dask graph to a single output.
    """
    c_mean, c_std, n_segments, n_usable = segment_coherence(
        vis, flag, times, scan, intervals, dt, min_fill)
    n_bl, n_series, n_int = c_mean.shape
    out = np.empty((n_bl, n_series, n_int, 4))
    for b in range(n_bl):
        for c in range(n_series):
            for k in range(n_int):
                out[b, c, k, 0] = c_mean[b, c, k]
                out[b, c, k, 1] = c_std[b, c, k]
                out[b, c, k, 2] = n_segments[b, c, k]
                out[b, c, k, 3] = n_usable[b, c]
    return out


def segment_coherence_dask(vis, flag, times, scan, intervals, dt, min_fill):
    """Dask wrapper of :func:`segment_coherence`, parallel over baseline chunks.

    ``vis`` (n_bl, n_time, n_series), ``flag`` (n_bl, n_time, n_flag) and
    ``scan`` (n_bl, n_time) are dask arrays chunked along baselines only (time
    and series in one chunk, since segments run along time); ``times`` and
    ``intervals`` are numpy arrays.  Returns a dask float64 array
    (n_bl, n_series, n_int, 4) with the fields of :data:`FIELDS`.
    """
    import dask.array as da

    intervals = np.ascontiguousarray(intervals, dtype=np.float64)
    times = np.ascontiguousarray(times, dtype=np.float64)
    vis = vis.rechunk({1: -1, 2: -1})
    flag = flag.rechunk((vis.chunks[0], -1, -1))
    scan = scan.rechunk((vis.chunks[0], -1))

    def block(vis_b, flag_b, scan_b):
        return segment_coherence_stacked(vis_b, flag_b, times, scan_b, intervals,
                                         float(dt), float(min_fill))

    return da.blockwise(block, ("bl", "series", "int", "field"),
                        vis, ("bl", "time", "series"),
                        flag, ("bl", "time", "flagcorr"),
                        scan, ("bl", "time"),
                        new_axes={"int": intervals.size, "field": len(FIELDS)},
                        concatenate=True, dtype=np.float64,
                        meta=np.empty((0, 0, 0, 0), dtype=np.float64))
