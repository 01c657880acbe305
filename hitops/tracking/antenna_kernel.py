"""Antenna-based phase-wrap tracking at the reference band.

Why: baseline-based PWC counts wraps from n = 0 at each baseline's first
sample.  A baseline whose two stations only see the source together after
one of them has accumulated wraps starts with the wrong n0 and its residual
carries a constant 2 pi eps k (Lee et al., fpt-arbitrary-ratios, Results).
The offsets differ from baseline to baseline and do not close, so they
survive into closure phases and images.  Here the wrap ambiguity lives in
the *antennas*:

1. :func:`solve_antenna_phases` - per time sample, a phase-only solve of
   V_pq = g_p conj(g_q) (point-source model, as CASA ``gaincal`` calmode 'p'
   or StEFCal, Salvini & Wijnholds 2014, A&A 571, A97: alternating
   per-antenna updates g_p <- arg(sum_q V_pq g_q), averaged with the previous
   iterate), referred to a reference antenna.  When the reference antenna
   changes, the new frame is rotated onto the previous sample's solution
   (circular mean over the antennas present in both) so each antenna's phase
   stays continuous;
2. any tracker of :mod:`hitops.tracking.count` / :mod:`hitops.tracking.smooth_kernel`
   on each antenna's phase series (the antenna solution has the SNR of all
   its baselines combined);
3. :func:`baseline_counts_from_antennas` - each baseline sample takes the
   2 pi lobe nearest the unwrapped antenna model A_p - A_q.

A baseline's count is then n_p - n_q plus a per-sample lobe choice, so a
constant count error k_p of antenna p enters every baseline as
2 pi eps (k_p - k_q): it cancels in every closure phase and is absorbed by
any later antenna-based phase calibration.  No reference column is needed.
"""

from __future__ import annotations

import numba
import numpy as np

TWO_PI = 2.0 * np.pi


@numba.njit(cache=True, nogil=True)
def _wrap(x):
    return x - TWO_PI * np.floor((x + np.pi) / TWO_PI)


@numba.njit(cache=True, nogil=True)
def _sample(vis, valid, ant1, ant2, t, v_re, v_im, use, present):
    """Copy time sample t's usable baselines into (v_re, v_im, use); mark the antennas present."""
    present[:] = False
    for b in range(vis.shape[0]):
        use[b] = False
        if valid[b, t] and ant1[b] != ant2[b]:
            v = vis[b, t]
            re = np.float64(v.real)
            im = np.float64(v.imag)
            if np.isfinite(re) and np.isfinite(im) and (re != 0.0 or im != 0.0):
                use[b] = True
                v_re[b] = re
                v_im[b] = im
                present[ant1[b]] = True
                present[ant2[b]] = True


@numba.njit(cache=True, nogil=True)
def _reference(refants, present):
    """The first of ``refants`` present, else the lowest-numbered present antenna, else -1."""
    n_ant = present.size
    for r in refants:
        if 0 <= r < n_ant and present[r]:
            return r
    for p in range(n_ant):
        if present[p]:
            return p
    return -1


@numba.njit(cache=True, nogil=True)
def _solve(v_re, v_im, use, ant1, ant2, present, g_re, g_im, n_iter, tol):
    """Phase-only StEFCal iterations on one sample, updating the unit gains (g_re, g_im)."""
    n_ant = g_re.size
    acc_re = np.zeros(n_ant)
    acc_im = np.zeros(n_ant)
    for it in range(n_iter):
        acc_re[:] = 0.0
        acc_im[:] = 0.0
        for b in range(v_re.size):
            if not use[b]:
                continue
            p = ant1[b]
            q = ant2[b]
            re = v_re[b]
            im = v_im[b]
            # V_pq g_q -> g_p ; conj(V_pq) g_p -> g_q
            acc_re[p] += re * g_re[q] - im * g_im[q]
            acc_im[p] += re * g_im[q] + im * g_re[q]
            acc_re[q] += re * g_re[p] + im * g_im[p]
            acc_im[q] += re * g_im[p] - im * g_re[p]
        change = 0.0
        for p in range(n_ant):
            if not present[p]:
                continue
            amp = np.hypot(acc_re[p], acc_im[p])
            if amp == 0.0:
                continue
            # every second iterate is averaged with the previous one (StEFCal's
            # damping, which stops the two-cycle oscillation), then renormalised
            if it % 2 == 1:
                n_re = 0.5 * (g_re[p] + acc_re[p] / amp)
                n_im = 0.5 * (g_im[p] + acc_im[p] / amp)
            else:
                n_re = acc_re[p] / amp
                n_im = acc_im[p] / amp
            n_amp = np.hypot(n_re, n_im)
            if n_amp == 0.0:
                n_re = acc_re[p] / amp
                n_im = acc_im[p] / amp
                n_amp = 1.0
            n_re /= n_amp
            n_im /= n_amp
            change = max(change, np.hypot(n_re - g_re[p], n_im - g_im[p]))
            g_re[p] = n_re
            g_im[p] = n_im
        if change < tol:
            break


@numba.njit(cache=True, nogil=True)
def _frame_offset(ant_phase, ant_valid, prev_t, present, g_re, g_im, ref_phase):
    """(angle, carried): the rotation of a new reference antenna's frame onto the previous
    sample's solutions (circular mean over the antennas in both); (0, False) when no
    antenna was present at both samples to carry the frame."""
    s_re = 0.0
    s_im = 0.0
    n_common = 0
    for p in range(present.size):
        if present[p] and ant_valid[p, prev_t]:
            d = ant_phase[p, prev_t] - (np.arctan2(g_im[p], g_re[p]) - ref_phase)
            s_re += np.cos(d)
            s_im += np.sin(d)
            n_common += 1
    if n_common > 0:
        return np.arctan2(s_im, s_re), True
    return 0.0, False


@numba.njit(cache=True, nogil=True)
def solve_antenna_phases(vis, valid, ant1, ant2, n_ant, refants, n_iter=30, tol=1e-4):
    """Per-sample phase-only antenna solutions at the reference band.

    vis: complex (n_bl, n_time), complex64 or complex128 (promoted to
    complex128 inside); valid: bool (n_bl, n_time); ant1, ant2: int64 (n_bl,);
    refants: int64 antenna indices in order of preference (the first present
    at a sample is used; when none is, the lowest-numbered present antenna).

    Returns ``(ant_phase, ant_valid, ref_used, frame_break)``:
    ant_phase float64 (n_ant, n_time) wrapped phases (NaN where unsolved),
    ant_valid bool (n_ant, n_time), ref_used int64 (n_time,) (-1: nothing
    solved), frame_break bool (n_time,): the reference changed and no antenna
    was present at both samples to carry the frame (antenna tracks must be
    treated as new segments there).
    """
    n_bl, n_time = vis.shape
    ant_phase = np.full((n_ant, n_time), np.nan)
    ant_valid = np.zeros((n_ant, n_time), np.bool_)
    ref_used = np.full(n_time, -1, np.int64)
    frame_break = np.zeros(n_time, np.bool_)
    g_re = np.ones(n_ant)
    g_im = np.zeros(n_ant)
    present = np.zeros(n_ant, np.bool_)
    offset = 0.0
    prev_t = -1
    prev_ref = -1
    # one time sample's baselines, copied contiguously (the grid is baseline-major)
    v_re = np.zeros(n_bl)
    v_im = np.zeros(n_bl)
    use = np.zeros(n_bl, np.bool_)
    for t in range(n_time):
        _sample(vis, valid, ant1, ant2, t, v_re, v_im, use, present)
        ref = _reference(refants, present)
        if ref < 0:
            continue
        # warm start from the previous solution; fresh antennas start at 1
        for p in range(n_ant):
            if not (prev_t >= 0 and ant_valid[p, prev_t]):
                g_re[p] = 1.0
                g_im[p] = 0.0
        _solve(v_re, v_im, use, ant1, ant2, present, g_re, g_im, n_iter, tol)
        ref_phase = np.arctan2(g_im[ref], g_re[ref])
        if prev_ref >= 0 and ref != prev_ref:
            # rotate the new frame onto the previous sample's solutions
            offset, carried = _frame_offset(ant_phase, ant_valid, prev_t, present, g_re, g_im,
                                            ref_phase)
            frame_break[t] = not carried
        for p in range(n_ant):
            if present[p]:
                ant_phase[p, t] = _wrap(np.arctan2(g_im[p], g_re[p]) - ref_phase + offset)
                ant_valid[p, t] = True
        ref_used[t] = ref
        prev_ref = ref
        prev_t = t
    return ant_phase, ant_valid, ref_used, frame_break


@numba.njit(cache=True, nogil=True)
def baseline_counts_from_antennas(ref_phase, valid, ant1, ant2, ant_phase, ant_valid, ant_counts):
    """Baseline wrap counts from tracked antenna phases.

    ref_phase float64 (n_bl, n_time) (wrapped baseline phases), valid bool
    (n_bl, n_time), ant_phase/ant_valid (n_ant, n_time) from
    :func:`solve_antenna_phases`, ant_counts int64 (n_ant, n_time) from any
    tracker.  Same sign convention as count_wraps: ``ref_phase - 2 pi n`` is
    the unwrapped phase; each valid sample takes the lobe nearest the
    unwrapped antenna model (A_p - A_q), A = ant_phase - 2 pi ant_counts.

    Returns ``(counts, unmodelled)``: counts int64 (n_bl, n_time) (invalid
    samples carry the previous count); unmodelled bool (n_bl, n_time) marks
    valid samples without both antenna solutions (they carry the previous
    count too).
    """
    n_bl, n_time = ref_phase.shape
    counts = np.zeros((n_bl, n_time), np.int64)
    unmodelled = np.zeros((n_bl, n_time), np.bool_)
    for b in range(n_bl):
        p = ant1[b]
        q = ant2[b]
        n_prev = 0
        for t in range(n_time):
            phase = ref_phase[b, t]
            if valid[b, t] and np.isfinite(phase):
                if ant_valid[p, t] and ant_valid[q, t]:
                    model = (ant_phase[p, t] - TWO_PI * ant_counts[p, t]) \
                        - (ant_phase[q, t] - TWO_PI * ant_counts[q, t])
                    n_prev = np.int64(np.round((phase - model) / TWO_PI))
                else:
                    unmodelled[b, t] = True
            counts[b, t] = n_prev
    return counts, unmodelled


@numba.njit(cache=True, nogil=True)
def closure_phases(phase, valid, ant1, ant2, triangles):
    """Closure phases (rad, wrapped) of baseline phases over antenna triangles.

    phase float64 (n_bl, n_time); triangles int64 (n_tri, 3) of antenna
    indices (p, q, r): closure = phi_pq + phi_qr + phi_rp, each term taken
    from whichever baseline orientation exists (negated if reversed).
    NaN where any of the three is missing.
    """
    n_bl, n_time = phase.shape
    n_tri = triangles.shape[0]
    out = np.full((n_tri, n_time), np.nan)
    for k in range(n_tri):
        legs = np.full(3, -1, np.int64)
        signs = np.zeros(3)
        for leg in range(3):
            a = triangles[k, leg]
            c = triangles[k, (leg + 1) % 3]
            for b in range(n_bl):
                if ant1[b] == a and ant2[b] == c:
                    legs[leg] = b
                    signs[leg] = 1.0
                elif ant1[b] == c and ant2[b] == a:
                    legs[leg] = b
                    signs[leg] = -1.0
        if legs[0] < 0 or legs[1] < 0 or legs[2] < 0:
            continue
        for t in range(n_time):
            if valid[legs[0], t] and valid[legs[1], t] and valid[legs[2], t]:
                s = 0.0
                for leg in range(3):
                    s += signs[leg] * phase[legs[leg], t]
                out[k, t] = _wrap(s)
    return out
