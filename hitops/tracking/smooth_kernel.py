"""Robust phase-wrap tracking of a reference-band phase series.

Same contract as :func:`hitops.tracking.count.count_wraps` (``ref_phase``
float64[n_time], ``valid`` bool[n_time] -> wrap counts int64[n_time], invalid
samples carrying the previous count, counts starting at 0), plus keyword
parameters and diagnostics.  Sign convention of the paper (Lee et al.,
fpt-arbitrary-ratios, eq. for phi_cal): the wrapped phase is the unwrapped
phase plus 2 pi n, so n increases by one when the phase crosses the -pi/+pi
boundary from the -pi side, and ``ref_phase - 2 pi n`` is the unwrapped phase.

Why not compare consecutive raw samples (naive Itoh tracking)?  At a
per-sample SNR rho = 2 one step in 300 fails and every failure is a
persistent slip (:mod:`hitops.tracking.theory`).  Here the wrap count is
read off a *smoothed* track instead:

1. segments: a run of invalid samples longer than ``max_gap`` starts a new
   segment, and so does an instrumental jump (below);
2. jumps: the phase difference between the mean unit phasors of the
   ``jump_window`` samples before and from each sample; a local maximum above
   ``jump_threshold`` that is not a wrap (a wrap does not move the phasor) is
   an instrumental jump;
3. smoothing: the sum S of the unit phasors exp(i phi) within +-``half_window``
   samples (same segment only).  Its phase has the noise of a W-sample mean,
   and two consecutive sums differ by at most two unit vectors, so the
   smoothed phase can only jump by more than pi where |S| <= 2;
4. unwrapping the smoothed phase; across a gap (<= ``max_gap``) the step is
   predicted from the phase rates on both sides (bridging), and across a
   segment boundary from the rates (long gap) or the measured jump;
5. snapping: each raw sample takes the 2 pi lobe nearest the smoothed
   unwrapped phase.  A raw sample whose noise exceeds pi is mis-snapped on
   its own only (a transient outlier), never shifting its successors.

Diagnostics (all length n_time): ``segment`` (segment id of each valid
sample, -1 where invalid), ``suspect`` (smoothed-phasor mean resultant below
``min_coherence``, or a smoothed step above pi/2: a slip is possible there),
``bridged`` (first valid sample after a bridged gap), ``jump`` (measured
jump in rad at the first sample after a detected jump, 0 elsewhere).
Segments after long gaps or jumps continue with the predicted lobe as a best
guess; the caller must treat their offsets as unresolved (resolve them with
antenna-based tracking or a reference) and report them.
"""

from __future__ import annotations

import numba
import numpy as np

TWO_PI = 2.0 * np.pi


@numba.njit(cache=True, nogil=True)
def _wrap(x):
    """x mapped to [-pi, pi)."""
    return x - TWO_PI * np.floor((x + np.pi) / TWO_PI)


@numba.njit(cache=True, nogil=True)
def _valid_samples(ref_phase, valid):
    n_time = ref_phase.size
    n_valid = 0
    for i in range(n_time):
        if valid[i] and np.isfinite(ref_phase[i]):
            n_valid += 1
    index = np.empty(n_valid, np.int64)
    k = 0
    for i in range(n_time):
        if valid[i] and np.isfinite(ref_phase[i]):
            index[k] = i
            k += 1
    return index


@numba.njit(cache=True, nogil=True)
def _prefix_phasors(phase):
    """Prefix sums (length m+1) of cos and sin of ``phase``."""
    m = phase.size
    pre_re = np.zeros(m + 1)
    pre_im = np.zeros(m + 1)
    for k in range(m):
        pre_re[k + 1] = pre_re[k] + np.cos(phase[k])
        pre_im[k + 1] = pre_im[k] + np.sin(phase[k])
    return pre_re, pre_im


@numba.njit(cache=True, nogil=True)
def segment_bounds(seg_first):
    """First index and one-past-last index of the segment holding each sample."""
    m = seg_first.size
    seg_lo = np.empty(m, np.int64)
    seg_hi = np.empty(m, np.int64)
    lo = 0
    for k in range(m):
        if seg_first[k]:
            lo = k
        seg_lo[k] = lo
    hi = m
    for k in range(m - 1, -1, -1):
        seg_hi[k] = hi
        if seg_first[k]:
            hi = k
    return seg_lo, seg_hi


@numba.njit(cache=True, nogil=True)
def _detect_jumps(index, pre_re, pre_im, seg_first, jump_window, jump_threshold, min_coherence):
    """Measured jump (rad) at each valid sample that starts after a jump, else 0.

    ``seg_first[k]`` marks valid samples that start a gap-segment; windows
    never cross those boundaries.
    """
    m = index.size
    stat = np.zeros(m)
    jumps = np.zeros(m)
    if jump_threshold <= 0.0 or jump_window < 1 or m < 2 * jump_window:
        return jumps
    # bounds of the gap-segment of every valid sample
    seg_lo, seg_hi = segment_bounds(seg_first)
    w = jump_window
    for k in range(m):
        if k - w < seg_lo[k] or k + w > seg_hi[k]:
            continue
        l_re = pre_re[k] - pre_re[k - w]
        l_im = pre_im[k] - pre_im[k - w]
        r_re = pre_re[k + w] - pre_re[k]
        r_im = pre_im[k + w] - pre_im[k]
        # both sides must hold a usable mean phasor
        if np.hypot(l_re, l_im) < min_coherence * w or np.hypot(r_re, r_im) < min_coherence * w:
            continue
        # arg(conj(L) R)
        stat[k] = np.arctan2(l_re * r_im - l_im * r_re, l_re * r_re + l_im * r_im)
    for k in range(m):
        a = abs(stat[k])
        if a <= jump_threshold:
            continue
        is_peak = True
        for j in range(max(seg_lo[k], k - w), min(seg_hi[k], k + w + 1)):
            if j < k and abs(stat[j]) >= a:
                is_peak = False
                break
            if j > k and abs(stat[j]) > a:
                is_peak = False
                break
        if is_peak:
            jumps[k] = stat[k]
    return jumps


@numba.njit(cache=True, nogil=True)
def _local_rate(index, track, k_from, k_to):
    """Phase rate (rad/sample) of an already unwrapped ``track`` between two valid samples."""
    span = index[k_to] - index[k_from]
    if span <= 0:
        return 0.0, False
    return (track[k_to] - track[k_from]) / span, True


@numba.njit(cache=True, nogil=True)
def _predicted_step(index, unwrapped, smooth_phase, k, seg_lo_before, seg_hi_after, base):
    """Predicted smoothed-phase change from valid sample k-1 to k across a gap.

    Mean of the phase rates over ``base`` samples before k-1 (already
    unwrapped) and after k (unwrapped locally here), times the gap length.
    """
    gap = index[k] - index[k - 1]
    n_rates = 0
    rate_sum = 0.0
    # rate before the gap
    j0 = k - 1
    while j0 - 1 >= seg_lo_before and index[k - 1] - index[j0 - 1] <= base:
        j0 -= 1
    if j0 < k - 1:
        rate, ok = _local_rate(index, unwrapped, j0, k - 1)
        if ok:
            rate_sum += rate
            n_rates += 1
    # rate after the gap: local Itoh unwrap of the smoothed phase
    j1 = k
    acc = 0.0
    while j1 + 1 < seg_hi_after and index[j1 + 1] - index[k] <= base:
        acc += _wrap(smooth_phase[j1 + 1] - smooth_phase[j1])
        j1 += 1
    if j1 > k:
        rate_sum += acc / (index[j1] - index[k])
        n_rates += 1
    if n_rates == 0:
        return 0.0
    return gap * rate_sum / n_rates


@numba.njit(cache=True, nogil=True)
def _segments(index, pre_re, pre_im, max_gap, jump_window, jump_threshold, min_coherence):
    """(first sample of a segment?, segment id, measured jump) of each valid sample.

    A run of invalid samples longer than ``max_gap`` starts a segment, and so
    does an instrumental jump (detected within the gap-segments).
    """
    m = index.size
    long_gap_first = np.zeros(m, np.bool_)
    long_gap_first[0] = True
    for k in range(1, m):
        if index[k] - index[k - 1] - 1 > max_gap:
            long_gap_first[k] = True
    jumps = _detect_jumps(index, pre_re, pre_im, long_gap_first, jump_window,
                          jump_threshold, min_coherence)
    seg_first = long_gap_first.copy()
    for k in range(m):
        if jumps[k] != 0.0:
            seg_first[k] = True
    seg_id = np.empty(m, np.int64)
    current = -1
    for k in range(m):
        if seg_first[k]:
            current += 1
        seg_id[k] = current
    return seg_first, seg_id, jumps


@numba.njit(cache=True, nogil=True)
def _smoothed(index, pre_re, pre_im, seg_first, seg_lo, seg_hi, half_window, half_windows):
    """Phase and mean resultant of the unit-phasor sum over +-h samples (by time index)
    within the segment; with ``half_windows`` each sample has its own h (e.g. from the
    local coherence time, which shrinks as sin(el)^(3/5) towards low elevation)."""
    m = index.size
    smooth_phase = np.empty(m)
    coherence = np.empty(m)
    h = max(half_window, 0)
    a = 0
    b = 0
    for k in range(m):
        if half_windows is None:
            if seg_first[k]:
                a = k
                b = k
            while index[a] < index[k] - h:
                a += 1
            if b < k + 1:
                b = k + 1
            while b < seg_hi[k] and index[b] <= index[k] + h:
                b += 1
        else:
            hk = max(half_windows[index[k]], 0)
            a = max(np.searchsorted(index, index[k] - hk), seg_lo[k])
            b = min(np.searchsorted(index, index[k] + hk, side="right"), seg_hi[k])
        s_re = pre_re[b] - pre_re[a]
        s_im = pre_im[b] - pre_im[a]
        smooth_phase[k] = np.arctan2(s_im, s_re)
        coherence[k] = np.hypot(s_re, s_im) / (b - a)
    return smooth_phase, coherence


@numba.njit(cache=True, nogil=True)
def _jump_prediction(index, unwrapped, seg_lo, k, jump, h, jump_window, base):
    """Smoothed phase predicted at k, the first sample after a jump: continue across it
    with its measured size (|jump| <= pi).  The statistic compares window means
    jump_window samples apart, while the one-sided smoothed phases either side of the
    boundary are about h+1 samples apart: correct the turbulent trend for it."""
    rate = 0.0
    j0 = k - 1
    while j0 - 1 >= seg_lo[k - 1] and index[k - 1] - index[j0 - 1] <= base:
        j0 -= 1
    if j0 < k - 1:
        rate, _ok = _local_rate(index, unwrapped, j0, k - 1)
    return unwrapped[k - 1] + jump + rate * (h + 1 - jump_window)


@numba.njit(cache=True, nogil=True)
def _unwrap_smoothed(index, smooth_phase, seg_first, seg_lo, seg_hi, jumps, h, jump_window,
                     max_gap, bridged, suspect):
    """Unwrapped smoothed phase, bridging gaps and crossing segment boundaries.

    Sets ``bridged`` at the first sample after a bridged gap and ``suspect``
    where the smoothed phase steps by more than pi/2 (outputs of the caller).
    """
    m = index.size
    unwrapped = np.empty(m)
    base = max(2 * h + 1, 3)
    for k in range(m):
        if k == 0:
            unwrapped[k] = smooth_phase[k]
            continue
        gap = index[k] - index[k - 1]
        if seg_first[k] and jumps[k] != 0.0:
            predicted = _jump_prediction(index, unwrapped, seg_lo, k, jumps[k], h, jump_window,
                                         base)
        elif gap > 1:
            # the rates are measured over max(2h+1, gap) samples, but never more
            # than max_gap + 1: beyond it the gap starts an unresolved segment anyway,
            # and a bounded reach lets calibrate chunk the time axis exactly with a
            # finite context (TrackingSetup.context, hitops.tracking.options)
            span = max(base, min(gap, max_gap + 1))
            predicted = unwrapped[k - 1] + _predicted_step(index, unwrapped, smooth_phase, k,
                                                           seg_lo[k - 1], seg_hi[k], span)
            if not seg_first[k]:
                bridged[index[k]] = True
        else:
            predicted = unwrapped[k - 1]
        step = _wrap(smooth_phase[k] - smooth_phase[k - 1] - (predicted - unwrapped[k - 1]))
        unwrapped[k] = predicted + step
        if not seg_first[k] and gap == 1 and abs(_wrap(smooth_phase[k] - smooth_phase[k - 1])) > 0.5 * np.pi:
            suspect[index[k]] = True
    return unwrapped


@numba.njit(cache=True, nogil=True)
def track_wraps_smooth(ref_phase, valid, half_window=5, max_gap=30, jump_window=5,
                       jump_threshold=0.0, min_coherence=0.2, half_windows=None):
    """Wrap counts from a smoothed unit-phasor track, with gap bridging and jump detection.

    Parameters (samples unless stated): ``half_window`` h, smoothing over 2h+1
    samples (0: no smoothing, i.e. snapping to the raw track); ``max_gap``,
    the longest run of invalid samples bridged by prediction; ``jump_window``
    and ``jump_threshold`` (rad; <= 0, the default, disables),
    instrumental-jump detection: size both with
    :func:`hitops.tracking.theory.recommended_jump_params` (coherence time and
    SNR), because a fixed threshold either misses jumps or flags turbulence;
    ``min_coherence``, mean resultant below which a smoothed sample is suspect;
    ``half_windows`` (optional int64[n_time]): a half-window per sample,
    overriding ``half_window`` for the smoothing (``half_window`` still sets
    the base of the gap-bridging rates), e.g. from the local coherence time
    (:func:`hitops.tracking.windows.half_windows`).

    Returns ``(counts, segment, suspect, bridged, jump)``; see the module doc.
    """
    n_time = ref_phase.size
    counts = np.zeros(n_time, np.int64)
    segment = np.full(n_time, -1, np.int64)
    suspect = np.zeros(n_time, np.bool_)
    bridged = np.zeros(n_time, np.bool_)
    jump = np.zeros(n_time)
    index = _valid_samples(ref_phase, valid)
    m = index.size
    if m == 0:
        return counts, segment, suspect, bridged, jump
    phase = np.empty(m)
    for k in range(m):
        phase[k] = ref_phase[index[k]]
    pre_re, pre_im = _prefix_phasors(phase)
    # 1.-2. segments: long gaps and instrumental jumps start them
    seg_first, seg_id, jumps = _segments(index, pre_re, pre_im, max_gap, jump_window,
                                         jump_threshold, min_coherence)
    seg_lo, seg_hi = segment_bounds(seg_first)
    # 3. smoothed phasor
    smooth_phase, coherence = _smoothed(index, pre_re, pre_im, seg_first, seg_lo, seg_hi,
                                        half_window, half_windows)
    # 4. unwrapped smoothed phase (marks bridged gaps and suspect steps)
    h = max(half_window, 0)
    unwrapped = _unwrap_smoothed(index, smooth_phase, seg_first, seg_lo, seg_hi, jumps, h,
                                 jump_window, max_gap, bridged, suspect)
    for k in range(m):
        if coherence[k] < min_coherence:
            suspect[index[k]] = True
    # 5. snap each raw sample to the lobe nearest the smoothed track
    n_prev = 0
    k = 0
    for i in range(n_time):
        if k < m and index[k] == i:
            n_prev = np.int64(np.round((phase[k] - unwrapped[k]) / TWO_PI))
            segment[i] = seg_id[k]
            jump[i] = jumps[k]
            k += 1
        counts[i] = n_prev
    return counts, segment, suspect, bridged, jump
