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
def baseline_sums(vis, flag, bl_of_row, hand_corr, n_bl):
    """Sums of unflagged visibilities per baseline, channel and hand.

    vis (n_row, n_chan, n_corr) complex; flag (n_row, n_chan, n_corr) bool;
    bl_of_row (n_row,) baseline index; hand_corr (n_hand,) the correlation index of
    each parallel hand.  Returns (sums (n_bl, n_chan, n_hand) complex128, counts
    (n_bl, n_chan, n_hand) int64).
    """
    n_row, n_chan = vis.shape[0], vis.shape[1]
    n_hand = hand_corr.shape[0]
    sums = np.zeros((n_bl, n_chan, n_hand), dtype=np.complex128)
    counts = np.zeros((n_bl, n_chan, n_hand), dtype=np.int64)
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


#: the phase error (rad) that weighs as much as one wrap's delay in the calibrator
#: scans' integer decision: the 2 pi eps n lattice's points lie 121 deg (n = 1) and
#: 3.6 deg (n = 3, at 35 ps) apart at 229.1 / 86 GHz, so a third of a turn keeps n = 1
#: far while a delay drift of a wrap between scans is still read from the phase
PHASE_PER_WRAP = np.pi / 3.0


@numba.njit(cache=True, nogil=True)
def _wrapped(x):
    return x - 2.0 * np.pi * np.round(x / (2.0 * np.pi))


@numba.njit(cache=True, nogil=True)
def _extrapolated(t, t1, v1, t2, v2, n_done):
    """The next value from the last two (a straight line), the last one alone after one."""
    if n_done < 2 or t2 == t1:
        return v2
    return v2 + (v2 - v1) * (t - t2) / (t2 - t1)


@numba.njit(cache=True, nogil=True)
def scan_integers(times, phase, delay, valid, wrap_delay, ratio):
    """Each calibrator scan's integer m of 2 pi R_k m from its phase and delay.

    What FPT leaves on a scan is the instrumental term (slow) plus 2 pi R_k m, one
    integer per scan and series (baseline and hand) because every scan's wrap count
    starts afresh: a delay m * wrap_delay (1 / nu_ref, 11.6 ps at 86 GHz) and a phase
    2 pi R_0 m at the window's centre on top of the instrumental ones.  Scan by scan,
    the instrumental phase and delay are predicted from the scans already resolved (a
    straight line through the last two, the last one alone after the first scan) and m
    is the integer whose (delay, phase) lies nearest what was measured, the delay in
    wraps and the phase in PHASE_PER_WRAP: the delay alone cannot tell an instrumental
    delay drift of a wrap between scans (0.14 ns/h at 5-min cycles) from m = 1, the
    phase alone cannot tell m = 3 (3.6 deg) from 0.  The first valid scan of a series is
    m = 0 (a constant per series, which the interpolated calibrator term carries).

    times (n_scan,) s; phase (rad at nu_0), delay (s), valid: (n_scan, n_series);
    wrap_delay s; ratio R_0.  Returns (m (n_scan, n_series) int64, 0 where not valid;
    margin (n_scan, n_series): the distance of the second-nearest integer less the
    nearest's, in those units; NaN where m was set, not measured).
    """
    n_scan, n_series = delay.shape
    m = np.zeros((n_scan, n_series), dtype=np.int64)
    margin = np.full((n_scan, n_series), np.nan)
    two_pi = 2.0 * np.pi
    for s in range(n_series):
        n_done = 0
        t1 = t2 = d1 = d2 = p1 = p2 = 0.0      # the last two resolved scans
        for j in range(n_scan):
            if not valid[j, s]:
                continue
            k = 0
            if n_done > 0:
                d_ex = (delay[j, s] - _extrapolated(times[j], t1, d1, t2, d2, n_done)) / wrap_delay
                p_ex = phase[j, s] - _extrapolated(times[j], t1, p1, t2, p2, n_done)
                centre = int(np.round(d_ex))
                best = second = 1e300
                for cand in range(centre - 4, centre + 5):
                    turns = ratio * cand
                    dp = _wrapped(p_ex - two_pi * (turns - np.round(turns))) / PHASE_PER_WRAP
                    cost = np.sqrt((d_ex - cand) ** 2 + dp ** 2)
                    if cost < best:
                        second, best, k = best, cost, cand
                    elif cost < second:
                        second = cost
                margin[j, s] = second - best
            m[j, s] = k
            turns = ratio * k
            d_now = delay[j, s] - k * wrap_delay
            p_now = phase[j, s] - two_pi * (turns - np.round(turns))
            if n_done > 0:   # the phase continued from the prediction: unwrapped in time
                p_pred = _extrapolated(times[j], t1, p1, t2, p2, n_done)
                p_now = p_pred + _wrapped(p_now - p_pred)
            t1, d1, p1 = t2, d2, p2
            t2, d2, p2 = times[j], d_now, p_now
            n_done += 1
    return m, margin
