"""Kernels of the calibrator step (source-frequency phase referencing): scan sums of a
calibrator's visibilities per baseline and channel, antenna phases from them, and the
antennas' phase and delay across a window.

After FPT the target band still carries Phi_inst - R*phi_inst per station (the paper's
eq. for Phi_FPT): slowly varying, the same on every source the stations look at.  A
calibrator observed in scans between the target's measures it (Rioja & Dodson 2011,
AJ 141, 114, "source-frequency phase referencing"): per calibrator scan the FPT output
is averaged coherently over the scan (the troposphere is gone), each channel's antenna
phases are solved from every baseline at once, and a phase plus a delay is fitted per
antenna across the channels.

Kernels are pure: they never mutate their inputs and allocate their outputs.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def add_baseline_sums(sums, counts, vis, flag, bl_of_row, hand_corr):
    """``sums`` and ``counts`` (n_bl, n_chan, n_hand) with the unflagged visibilities of
    these rows added, row after row: returned as new arrays (the inputs are not changed).

    vis (n_row, n_chan, n_corr) complex; flag (n_row, n_chan, n_corr) bool;
    bl_of_row (n_row,) baseline index; hand_corr (n_hand,) the correlation index of
    each parallel hand.  Adding chunk after chunk gives the same sums, bit for bit, as
    one call on all the rows: each element takes the same additions in the same order.
    """
    n_row, n_chan = vis.shape[0], vis.shape[1]
    n_hand = hand_corr.shape[0]
    sums = sums.copy()          # the caller's arrays stay as they were
    counts = counts.copy()
    for r in range(n_row):
        b = bl_of_row[r]
        for k in range(n_chan):
            for h in range(n_hand):
                c = hand_corr[h]
                v = vis[r, k, c]
                if flag[r, k, c] or not (np.isfinite(v.real) and np.isfinite(v.imag)):
                    continue
                sums[b, k, h] += v
                counts[b, k, h] += 1
    return sums, counts


def baseline_sums(vis, flag, bl_of_row, hand_corr, n_bl):
    """Sums of unflagged visibilities per baseline, channel and hand: (sums (n_bl, n_chan,
    n_hand) complex128, counts (n_bl, n_chan, n_hand) int64); :func:`add_baseline_sums`
    from zeros."""
    shape = (n_bl, vis.shape[1], len(hand_corr))
    return add_baseline_sums(np.zeros(shape, np.complex128), np.zeros(shape, np.int64), vis,
                             flag, np.asarray(bl_of_row, np.int64),
                             np.asarray(hand_corr, np.int64))


@numba.njit(cache=True, nogil=True)
def antenna_phasors(sums, counts, ant1, ant2, n_ant, refant, n_iter):
    """Unit antenna phasors g_p per channel and hand with V_pq ~ g_p conj(g_q).

    sums, counts: :func:`baseline_sums` (n_bl, n_chan, n_hand); ant1, ant2 (n_bl,).
    Each iteration sets g_p to the phase of sum_q V_pq g_q (plus conj(V_qp) g_q),
    the least-squares update of a phase-only solve, averaged with the previous value
    (which keeps it from oscillating); the result is referred to ``refant`` (its
    phase 0), or to the lowest-numbered antenna with data where refant has none.
    Returns (g (n_ant, n_chan, n_hand) complex128, 0 where an antenna has no
    baseline; solved (n_ant, n_chan, n_hand) bool).
    """
    n_bl, n_chan, n_hand = sums.shape
    g = np.zeros((n_ant, n_chan, n_hand), dtype=np.complex128)
    solved = np.zeros((n_ant, n_chan, n_hand), dtype=np.bool_)
    for k in range(n_chan):
        for h in range(n_hand):
            for b in range(n_bl):
                if counts[b, k, h] > 0:
                    solved[ant1[b], k, h] = True
                    solved[ant2[b], k, h] = True
            cur = np.zeros(n_ant, dtype=np.complex128)
            for a in range(n_ant):
                if solved[a, k, h]:
                    cur[a] = 1.0
            for _ in range(n_iter):
                acc = np.zeros(n_ant, dtype=np.complex128)
                for b in range(n_bl):
                    if counts[b, k, h] == 0:
                        continue
                    v = sums[b, k, h] / counts[b, k, h]
                    p, q = ant1[b], ant2[b]
                    acc[p] += v * cur[q]
                    acc[q] += np.conj(v) * cur[p]
                for a in range(n_ant):
                    if solved[a, k, h] and abs(acc[a]) > 0.0:
                        new = acc[a] / abs(acc[a]) + cur[a]
                        if abs(new) > 0.0:
                            cur[a] = new / abs(new)
            ref = refant
            if not solved[ref, k, h]:
                ref = -1
                for a in range(n_ant):
                    if solved[a, k, h]:
                        ref = a
                        break
            if ref < 0:
                continue
            rot = np.conj(cur[ref])
            for a in range(n_ant):
                if solved[a, k, h]:
                    g[a, k, h] = cur[a] * rot
    return g, solved


@numba.njit(cache=True, nogil=True)
def phase_and_delay(g, solved, chan_offset):
    """Each antenna's phase at chan_offset = 0 and delay across the channels.

    g, solved: :func:`antenna_phasors` (n_ant, n_chan, n_hand); chan_offset (n_chan,)
    nu_k - nu_0 in Hz, increasing.  The phase is unwrapped along the solved channels
    (a step > pi between neighbours is a wrap: exact while |delay| x the channel
    spacing < 1/2) and a straight line phase + 2 pi chan_offset delay fitted by least
    squares; one solved channel gives its phase and delay 0.  Returns (phase (n_ant,
    n_hand) rad in (-pi, pi], delay (n_ant, n_hand) s, valid (n_ant, n_hand) bool).
    """
    n_ant, n_chan, n_hand = g.shape
    phase = np.zeros((n_ant, n_hand))
    delay = np.zeros((n_ant, n_hand))
    valid = np.zeros((n_ant, n_hand), dtype=np.bool_)
    two_pi = 2.0 * np.pi
    for a in range(n_ant):
        for h in range(n_hand):
            n = 0
            sx = sy = sxx = sxy = 0.0
            last = 0.0
            for k in range(n_chan):
                if not solved[a, k, h]:
                    continue
                y = np.angle(g[a, k, h])
                if n > 0:
                    y -= two_pi * np.round((y - last) / two_pi)
                last = y
                x = chan_offset[k]
                n += 1
                sx += x
                sy += y
                sxx += x * x
                sxy += x * y
            if n == 0:
                continue
            valid[a, h] = True
            det = n * sxx - sx * sx
            slope = (n * sxy - sx * sy) / det if n > 1 and det > 0.0 else 0.0
            intercept = (sy - slope * sx) / n
            delay[a, h] = slope / two_pi
            phase[a, h] = np.angle(np.exp(1j * intercept))
    return phase, delay, valid


@numba.njit(cache=True, nogil=True)
def model_residuals(sums, counts, ant1, ant2, phase, delay, valid, chan_offset):
    """What the antenna model leaves on each baseline: sum of V_pq exp(-i (m_p - m_q)),
    m_a = phase[a, h] + 2 pi chan_offset[k] delay[a, h].

    sums, counts: :func:`baseline_sums` (n_bl, n_chan, n_hand); phase, delay, valid:
    :func:`phase_and_delay` (n_ant, n_hand).  Returns (n_bl, n_chan, n_hand)
    complex128, 0 where a baseline has no data or an antenna no solution.  On a point
    source its phase is the part no antenna term can absorb: with the count tracker's
    per-baseline wrap counts, 2 pi R_k (m_pq - m_p + m_q) per baseline (a whole
    number m of turns of the reference phase), the same on every field.
    """
    n_bl, n_chan, n_hand = sums.shape
    out = np.zeros((n_bl, n_chan, n_hand), dtype=np.complex128)
    two_pi = 2.0 * np.pi
    for b in range(n_bl):
        p, q = ant1[b], ant2[b]
        for h in range(n_hand):
            if not (valid[p, h] and valid[q, h]):
                continue
            for k in range(n_chan):
                if counts[b, k, h] == 0:
                    continue
                model = (phase[p, h] - phase[q, h]
                         + two_pi * chan_offset[k] * (delay[p, h] - delay[q, h]))
                out[b, k, h] = sums[b, k, h] * np.exp(-1j * model)
    return out


#: what weighs as one unit in the calibrator scans' integer decision: a delay error of
#: DELAY_SCALE_WRAPS wraps, a phase error of PHASE_SCALE rad.  Across 2 GHz the delay
#: is the coarse measure (11.6 ps per wrap against ~4.5 ps rms from 15 samples of SNR 4
#: per channel) and the phase at the centre the fine one (< 1 deg there): the 2 pi eps n
#: lattice's points lie 121 deg (n = 1) and 3.6 deg (n = 3, at 3 wraps) apart at
#: 229.1 / 86 GHz, so the phase picks n among its neighbours and the delay among every
#: third; the phase scale leaves room for the instrumental drift between two scans
DELAY_SCALE_WRAPS = 1.5
PHASE_SCALE = np.pi / 6.0
#: resolved scans the sequential pass's delay prediction is fitted through (a straight
#: line), and the sweeps of the refinement against every other scan after it
DELAY_FIT_SCANS = 8
REFINE_SWEEPS = 3


@numba.njit(cache=True, nogil=True)
def _wrapped(x):
    return x - 2.0 * np.pi * np.round(x / (2.0 * np.pi))


@numba.njit(cache=True, nogil=True)
def _line_at(t, times, values, n):
    """A least-squares straight line through the n (times, values) given, at t; their
    one value for n = 1."""
    if n == 1:
        return values[0]
    mt = mv = 0.0
    for i in range(n):
        mt += times[i] / n
        mv += values[i] / n
    sxx = sxy = 0.0
    for i in range(n):
        sxx += (times[i] - mt) ** 2
        sxy += (times[i] - mt) * (values[i] - mv)
    return mv + (sxy / sxx) * (t - mt) if sxx > 0.0 else mv


@numba.njit(cache=True, nogil=True)
def _nearest_integer(d_ex, p_ex, ratio):
    """(m, margin): the integer whose (delay, phase) = (m wraps, 2 pi R_0 m) lies nearest
    the excess measured (``d_ex`` wraps, ``p_ex`` rad), and how much further the next is."""
    centre = int(np.round(d_ex))
    best = second = 1e300
    k = 0
    for cand in range(centre - 6, centre + 7):
        turns = ratio * cand
        dp = _wrapped(p_ex - 2.0 * np.pi * (turns - np.round(turns))) / PHASE_SCALE
        cost = np.sqrt(((d_ex - cand) / DELAY_SCALE_WRAPS) ** 2 + dp ** 2)
        if cost < best:
            second, best, k = best, cost, cand
        elif cost < second:
            second = cost
    return k, second - best


@numba.njit(cache=True, nogil=True)
def _refined(times, phase, delay, m, margin, wrap_delay, ratio, sweeps):
    """Each scan's integer decided again against every other scan of its series: the
    delay predicted by a straight line through all the others (the sequential pass
    predicts the early scans from one or two), the phase by the straight line between
    its neighbours.  phase, delay, m, margin: one series' valid scans, changed in place
    (the caller's own copies)."""
    n = times.size
    two_pi = 2.0 * np.pi
    if n < 3:
        return
    others_t = np.zeros(n - 1)
    others_d = np.zeros(n - 1)
    for _ in range(sweeps):
        clean_d = delay - m * wrap_delay
        clean_p = np.zeros(n)
        for j in range(n):
            turns = ratio * m[j]
            clean_p[j] = phase[j] - two_pi * (turns - np.round(turns))
            if j > 0:     # unwrapped in time
                clean_p[j] = clean_p[j - 1] + _wrapped(clean_p[j] - clean_p[j - 1])
        for j in range(n):
            i = 0
            for o in range(n):
                if o != j:
                    others_t[i] = times[o]
                    others_d[i] = clean_d[o]
                    i += 1
            d_pred = _line_at(times[j], others_t, others_d, n - 1)
            lo, hi = (j - 1, j + 1) if 0 < j < n - 1 else ((1, 2) if j == 0 else (n - 3, n - 2))
            p_pred = clean_p[lo] + (clean_p[hi] - clean_p[lo]) * (times[j] - times[lo]) \
                / (times[hi] - times[lo])
            k, gap = _nearest_integer((delay[j] - d_pred) / wrap_delay,
                                      phase[j] - p_pred, ratio)
            m[j] = k
            margin[j] = gap


@numba.njit(cache=True, nogil=True)
def _misfit(times, phase, delay, m, wrap_delay, ratio):
    """How far a series' scans, their integers removed, lie from a straight line in delay
    and in (time-unwrapped) phase: the sum of squares in DELAY_SCALE_WRAPS and PHASE_SCALE."""
    n = times.size
    clean_d = (delay - m * wrap_delay) / (DELAY_SCALE_WRAPS * wrap_delay)
    clean_p = np.zeros(n)
    for j in range(n):
        turns = ratio * m[j]
        clean_p[j] = phase[j] - 2.0 * np.pi * (turns - np.round(turns))
        if j > 0:
            clean_p[j] = clean_p[j - 1] + _wrapped(clean_p[j] - clean_p[j - 1])
    clean_p = clean_p / PHASE_SCALE
    total = 0.0
    for values in (clean_d, clean_p):
        for j in range(n):
            total += (values[j] - _line_at(times[j], times, values, n)) ** 2
    return total


@numba.njit(cache=True, nogil=True)
def _phase_preserving_step(ratio):
    """The smallest integer step d (1..12) whose 2 pi R_0 d lies nearest a whole turn: the
    step a delay error can take unseen by the phase (3 at 229.1 / 86 GHz: 2.9 deg)."""
    best, step = 1e300, 1
    for d in range(1, 13):
        turns = ratio * d
        off = abs(turns - np.round(turns))
        if off < best:
            best, step = off, d
    return step


@numba.njit(cache=True, nogil=True)
def _block_shifted(times, phase, delay, m, wrap_delay, ratio):
    """Every block of scans from one scan to the last moved by the phase-preserving step
    (up or down) while that lowers the series' misfit: a wrong integer decided early is
    carried by the predictions to every later scan, and no single scan's change undoes
    it.  m changed in place."""
    n = times.size
    step = _phase_preserving_step(ratio)
    now = _misfit(times, phase, delay, m, wrap_delay, ratio)
    for _ in range(n):
        improved = False
        for j in range(1, n):
            for sign in (-1, 1):
                trial = m.copy()
                trial[j:] += sign * step
                cost = _misfit(times, phase, delay, trial, wrap_delay, ratio)
                if cost < now - 1e-9:
                    m[:] = trial
                    now = cost
                    improved = True
        if not improved:
            break


@numba.njit(cache=True, nogil=True)
def scan_integers(times, phase, delay, valid, wrap_delay, ratio):
    """Each calibrator scan's integer m of 2 pi R_k m from its phase and delay.

    What FPT leaves on a scan is the instrumental term (slow) plus 2 pi R_k m, one
    integer per scan and series (baseline and hand) because every scan's wrap count
    starts afresh: a delay m * wrap_delay (1 / nu_ref, 11.6 ps at 86 GHz) and a phase
    2 pi R_0 m at the window's centre on top of the instrumental ones.  Scan by scan,
    the instrumental delay is predicted by a straight line through the last
    DELAY_FIT_SCANS resolved scans and the phase by one through the last two (their
    last values after the first scan), and m is the integer whose (delay, phase) lies
    nearest what was measured, in DELAY_SCALE_WRAPS and PHASE_SCALE: the delay alone
    cannot tell an instrumental delay drift of a wrap between scans from m = 1 nor is
    it precise across a narrow window, the phase alone cannot tell m = 3 (3.6 deg) from
    0.  Then blocks of scans from one scan to the last are moved by the phase-preserving
    step while that brings the series nearer a straight line (``_block_shifted``), and
    each scan is decided again against all the others (``_refined``).  The first valid
    scan of a series is m = 0 (a constant per series, which the interpolated calibrator
    term carries to the target).

    times (n_scan,) s; phase (rad at nu_0), delay (s), valid: (n_scan, n_series);
    wrap_delay s; ratio R_0.  Returns (m (n_scan, n_series) int64, 0 where not valid;
    margin (n_scan, n_series): the distance of the second-nearest integer less the
    nearest's, in those units; NaN where m was set, not measured).
    """
    n_scan, n_series = delay.shape
    m = np.zeros((n_scan, n_series), dtype=np.int64)
    margin = np.full((n_scan, n_series), np.nan)
    two_pi = 2.0 * np.pi
    done_t = np.zeros(n_scan)
    done_d = np.zeros(n_scan)
    done_p = np.zeros(n_scan)
    for s in range(n_series):
        n_done = 0
        for j in range(n_scan):
            if not valid[j, s]:
                continue
            k = 0
            p_pred = phase[j, s]
            if n_done > 0:
                first = max(0, n_done - DELAY_FIT_SCANS)
                d_pred = _line_at(times[j], done_t[first:n_done], done_d[first:n_done],
                                  n_done - first)
                p_first = max(0, n_done - 2)
                p_pred = _line_at(times[j], done_t[p_first:n_done], done_p[p_first:n_done],
                                  n_done - p_first)
                k, margin[j, s] = _nearest_integer((delay[j, s] - d_pred) / wrap_delay,
                                                   phase[j, s] - p_pred, ratio)
            m[j, s] = k
            turns = ratio * k
            p_now = phase[j, s] - two_pi * (turns - np.round(turns))
            done_t[n_done] = times[j]
            done_d[n_done] = delay[j, s] - k * wrap_delay
            # the phase continued from the prediction: unwrapped in time
            done_p[n_done] = p_pred + _wrapped(p_now - p_pred)
            n_done += 1
        idx = np.flatnonzero(valid[:, s])
        if idx.size >= 3:
            m_s, margin_s = m[idx, s].copy(), margin[idx, s].copy()
            _block_shifted(times[idx], phase[idx, s], delay[idx, s], m_s, wrap_delay, ratio)
            _refined(times[idx], phase[idx, s].copy(), delay[idx, s].copy(), m_s, margin_s,
                     wrap_delay, ratio, REFINE_SWEEPS)
            m[idx, s] = m_s - m_s[0]     # the first valid scan stays the zero
            margin[idx, s] = margin_s
            margin[idx[0], s] = np.nan
    return m, margin


@numba.njit(cache=True, nogil=True)
def times_factors(data, factors):
    """``data * factors`` (both (n_row, n_chan, n_corr)) as complex64, one scalar product
    per sample: numpy's complex64 multiply rounds the last bit differently in its vector
    body and at its scalar edges, which samples fall where moving with the arrays' places
    in memory (measured: 32 932 samples of a 4200-row product differed between two
    layouts), so a run's output moved with its chunking."""
    n_row, n_chan, n_corr = data.shape
    out = np.empty((n_row, n_chan, n_corr), np.complex64)
    for r in range(n_row):
        for k in range(n_chan):
            for c in range(n_corr):
                out[r, k, c] = data[r, k, c] * factors[r, k, c]
    return out
