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
