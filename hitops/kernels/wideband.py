"""Wideband FPT kernels: one reference phase per row from many channels, one ratio per target channel.

The troposphere is non-dispersive: it adds an excess path L(t), so channel k of
either band sees the phase 2*pi*nu_k*L(t)/c (GUIDE.md, "Wideband"; issue 26).
Two consequences shape these kernels:

* The reference band's channels all carry the same L(t), as a phase that grows
  linearly with frequency (a delay tau = L/c, plus any residual instrumental
  delay).  A plain vector average over a window loses amplitude as
  |sinc(pi*B*tau)| and, when channels are flagged unevenly, refers the phase to
  the mean frequency of the usable channels rather than a stated one.
  :func:`row_delays` fits tau per row and correlation from the lag-1 product
  of neighbouring channels, and :func:`reference_phasors` averages the
  channels after taking that slope out, so the result is the phase at the
  stated reference frequency nu_ref with no decorrelation.
* The target channel k needs its own ratio R_k = nu_k / nu_ref.  With the
  reference wrap count n(t) (one per series, counted on the reduced phase) and
  the unwrapped reference phase psi = phi - 2*pi*(n + n0), the correction is
  exp(-i*R_k*psi): the paper's PWC, Phi - R*phi + 2*pi*eps*n, per channel
  (R_k*2*pi*n differs from 2*pi*eps_k*n by a whole number of turns).  One ratio
  per window instead leaves 2*pi*(nu_k - nu_window)*L/c, radians at a 2-GHz
  window's edge for a few centimetres of path.

Kernels are pure: they never mutate their inputs and allocate their outputs.
:func:`reference_phasors_dask` and :func:`apply_channel_ratios_dask` are the
thin dask wrappers, mapping the kernels over row chunks.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .fpt import TWO_PI, usable

@numba.njit(cache=True, nogil=True, inline="always")
def cis(x):
    """exp(i*x) as complex128."""
    return complex(math.cos(x), math.sin(x))


@numba.njit(cache=True, nogil=True)
def evenly_spaced(values):
    """True when ``values`` step evenly (to 1e-9 of the step), as a window's channels do."""
    n = values.shape[0]
    if n < 3:
        return True
    step = (values[n - 1] - values[0]) / (n - 1)
    for k in range(1, n):
        if abs(values[k] - values[0] - k * step) > 1e-9 * abs(step):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def row_delays(vis, ok, chan_freq):
    """Delay (seconds) of each (row, correlation) across a window's channels.

    vis: (n_row, n_chan, n_corr) complex; ok: same shape, bool (unflagged);
    chan_freq: (n_chan,) Hz, increasing (hitops/calibrate/groups.py checks it); the
    spacing taken is the window's mean, exact for evenly spaced channels (as
    correlators deliver them), approximate otherwise.
    The delay is arg(sum_k V_{k+1} conj(V_k)) / (2*pi*dnu): the lag-1 product
    of neighbouring channels weighted by their amplitudes, unambiguous for
    |tau| < 1 / (2*dnu) (4 ns for 125-MHz channels).  Rows with no usable
    neighbouring pair get NaN.
    """
    n_row, n_chan, n_corr = vis.shape
    delay = np.full((n_row, n_corr), np.nan)
    if n_chan < 2:
        return delay
    dnu = (chan_freq[n_chan - 1] - chan_freq[0]) / (n_chan - 1)
    for r in range(n_row):
        for c in range(n_corr):
            acc = 0j
            pairs = 0
            for k in range(n_chan - 1):
                a = vis[r, k, c]
                b = vis[r, k + 1, c]
                if ok[r, k, c] and ok[r, k + 1, c] and usable(a) and usable(b):
                    acc += b * a.conjugate()
                    pairs += 1
            if pairs > 0 and acc != 0j:
                delay[r, c] = math.atan2(acc.imag, acc.real) / (TWO_PI * dnu)
    return delay


@numba.njit(cache=True, nogil=True)
def reference_phasors(vis, ok, chan_freq, ref_freq, delay):
    """One visibility per (row, correlation), referred to ``ref_freq`` with the delay removed.

    vis/ok: (n_row, n_chan, n_corr); chan_freq (n_chan,) Hz; ref_freq Hz;
    delay: (n_row, n_corr) seconds from :func:`row_delays` (NaN: taken as 0,
    which is exact only when the one usable channel sits at ``ref_freq``).
    Returns (mean of V_k * exp(-2*pi*i*(nu_k - ref_freq)*tau) over the usable
    channels, complex128 (n_row, n_corr); usable, bool (n_row, n_corr)).
    """
    n_row, n_chan, n_corr = vis.shape
    out = np.zeros((n_row, n_corr), dtype=np.complex128)
    good = np.zeros((n_row, n_corr), dtype=np.bool_)
    even = evenly_spaced(chan_freq)
    dnu = (chan_freq[n_chan - 1] - chan_freq[0]) / max(n_chan - 1, 1)
    for r in range(n_row):
        for c in range(n_corr):
            tau = delay[r, c]
            if not math.isfinite(tau):
                tau = 0.0
            # evenly spaced channels: one sin/cos per row, the rest by recurrence (the
            # product's rounding grows as n_chan * 1e-16, far below any phase that matters)
            rotor = cis(-TWO_PI * (chan_freq[0] - ref_freq) * tau)
            step = cis(-TWO_PI * dnu * tau)
            acc = 0j
            count = 0
            for k in range(n_chan):
                if not even:
                    rotor = cis(-TWO_PI * (chan_freq[k] - ref_freq) * tau)
                v = vis[r, k, c]
                if ok[r, k, c] and usable(v):
                    acc += v * rotor
                    count += 1
                rotor *= step
            if count > 0 and acc != 0j:
                out[r, c] = acc / count
                good[r, c] = True
    return out, good


@numba.njit(cache=True, nogil=True)
def row_validity(data, flag, flag_row):
    """(n_row, n_corr) bool: some channel of the row is unflagged and usable.

    What the target band's reduction would call valid (:func:`reference_phasors`, whose
    mean is non-zero unless the usable channels cancel exactly), without reducing: PWC
    and CFPT need only this of the target.
    """
    n_row, n_chan, n_corr = data.shape
    out = np.zeros((n_row, n_corr), dtype=np.bool_)
    for r in range(n_row):
        if flag_row[r]:
            continue
        for c in range(n_corr):
            for k in range(n_chan):
                if not flag[r, k, c] and usable(data[r, k, c]):
                    out[r, c] = True
                    break
    return out


def gather_ok(rows, ok):
    """(n_bl, n_corr, n_time) validity of the cells from a row validity ``ok`` (n_row,
    n_corr) and the row grid ``rows`` (n_bl, n_time), -1 for none."""
    has_row = rows >= 0
    cells = ok[np.where(has_row, rows, 0)] & has_row[:, :, None]     # (n_bl, n_time, n_corr)
    return np.ascontiguousarray(cells.transpose(0, 2, 1))


@numba.njit(cache=True, nogil=True)
def plain_average(vis, ok):
    """The vector average of the usable channels (what ``--average-channels`` does).

    Kept beside :func:`reference_phasors` so the docs and tests can measure
    what the delay fit buys.  Returns (complex128 (n_row, n_corr), usable).
    """
    n_row, n_chan, n_corr = vis.shape
    out = np.zeros((n_row, n_corr), dtype=np.complex128)
    good = np.zeros((n_row, n_corr), dtype=np.bool_)
    for r in range(n_row):
        for c in range(n_corr):
            acc = 0j
            count = 0
            for k in range(n_chan):
                v = vis[r, k, c]
                if ok[r, k, c] and usable(v):
                    acc += v
                    count += 1
            if count > 0 and acc != 0j:
                out[r, c] = acc / count
                good[r, c] = True
    return out, good


@numba.njit(cache=True, nogil=True)
def apply_channel_ratios(tgt_vis, tgt_ok, ref_phase, ref_valid, ratios):
    """FPT-calibrated target visibilities, one ratio per channel.

    tgt_vis/tgt_ok: (n_row, n_chan, n_corr) target rows; ref_phase: (n_row, n_corr)
    float64, the reference phase matched to each target row (unwrapped,
    phi - 2*pi*(n + n0), for PWC; wrapped for CFPT); ref_valid: (n_row, n_corr);
    ratios: (n_chan,) R_k = nu_k / nu_ref.  PWC and CFPT share the formula,
    exp(-i*R_k*phase); what differs is the phase passed in.  CWU needs no kernel
    of its own: rewrapping cancels the target's unwrap, so it equals PWC with
    the same reference count (GUIDE.md section 1).
    Returns (calibrated visibilities complex64, zero where not calibrated;
    calibrated bool), both (n_row, n_chan, n_corr).
    """
    n_row, n_chan, n_corr = tgt_vis.shape
    out = np.zeros((n_row, n_chan, n_corr), dtype=np.complex64)
    calibrated = np.zeros((n_row, n_chan, n_corr), dtype=np.bool_)
    even = evenly_spaced(ratios)
    d_ratio = (ratios[n_chan - 1] - ratios[0]) / max(n_chan - 1, 1)
    for r in range(n_row):
        for c in range(n_corr):
            if not ref_valid[r, c]:
                continue
            phase = ref_phase[r, c]
            if not math.isfinite(phase):
                continue
            # R_k * phase can reach ~1e5 rad on a long track: float64 keeps it to ~1e-11 rad;
            # evenly spaced channels take one sin/cos per row and a recurrence across them
            rotor = cis(-ratios[0] * phase)
            step = cis(-d_ratio * phase)
            for k in range(n_chan):
                if not even:
                    rotor = cis(-ratios[k] * phase)
                v = tgt_vis[r, k, c]
                if tgt_ok[r, k, c] and usable(v):
                    out[r, k, c] = v * rotor
                    calibrated[r, k, c] = True
                rotor *= step
    return out, calibrated


def unwrapped_reference(ref_phase, wraps, n0=None):
    """phi - 2*pi*(n + n0): the reference phase with its counted (and n0) turns put back.

    ``wraps`` int64 counts from :mod:`hitops.tracking` (same shape as
    ``ref_phase``); ``n0`` an integer offset broadcastable to it (the n0 step's
    integer, per series and scan), or None.
    """
    turns = wraps if n0 is None else wraps + n0
    return ref_phase - TWO_PI * turns


def reference_phasors_dask(vis, ok, chan_freq, ref_freq):
    """:func:`row_delays` then :func:`reference_phasors` over row chunks of dask arrays.

    vis/ok: dask (n_row, n_chan, n_corr) chunked along rows only.  Returns two dask
    arrays (n_row, n_corr): the reduced visibilities and their usability.
    """
    import dask.array as da

    chan_freq = np.asarray(chan_freq, dtype=np.float64)

    def block(vis_b, ok_b):
        delay = row_delays(vis_b, ok_b, chan_freq)
        reduced, good = reference_phasors(vis_b, ok_b, chan_freq, float(ref_freq), delay)
        return np.stack([reduced, good.astype(np.complex128)], axis=-1)

    vis = vis.rechunk({1: -1, 2: -1})
    ok = ok.rechunk(vis.chunks)
    stacked = da.blockwise(block, ("row", "corr", "part"), vis, ("row", "chan", "corr"),
                           ok, ("row", "chan", "corr"), new_axes={"part": 2},
                           concatenate=True, dtype=np.complex128)
    return stacked[..., 0], stacked[..., 1].real.astype(bool)


def apply_channel_ratios_dask(tgt_vis, tgt_ok, ref_phase, ref_valid, ratios):
    """:func:`apply_channel_ratios` over row chunks of dask arrays (rows only chunked).

    Returns the calibrated visibilities (dask, complex64, like ``tgt_vis``); the
    calibrated mask is ``result != 0``.
    """
    import dask.array as da

    ratios = np.asarray(ratios, dtype=np.float64)
    tgt_vis = tgt_vis.rechunk({1: -1, 2: -1})
    rows = tgt_vis.chunks[0]
    tgt_ok = tgt_ok.rechunk(tgt_vis.chunks)
    ref_phase = da.asarray(ref_phase).rechunk((rows, -1))
    ref_valid = da.asarray(ref_valid).rechunk((rows, -1))

    def block(vis_b, ok_b, phase_b, valid_b):
        return apply_channel_ratios(vis_b, ok_b, phase_b, valid_b, ratios)[0]

    return da.blockwise(block, ("row", "chan", "corr"), tgt_vis, ("row", "chan", "corr"),
                        tgt_ok, ("row", "chan", "corr"), ref_phase, ("row", "corr"),
                        ref_valid, ("row", "corr"), concatenate=True, dtype=np.complex64)


@numba.njit(cache=True, nogil=True)
def channel_offset_scores(chan_sums, ratios, candidates):
    """How well each n0 candidate explains the per-channel offsets of a PWC output.

    chan_sums: (n_chan,) complex, the sum over a series' samples of
    exp(i*(Phi_ref - Phi_out)) in each target channel (Phi_ref from a reference
    calibration or model, Phi_out the PWC output counted from n'(t0) = 0);
    ratios: (n_chan,) R_j; candidates: (n_k,) int64.  A count that is wrong by
    n0 turns leaves channel j off by 2*pi*R_j*n0 (mod 2*pi), so candidate k's
    score is Re(sum_j z_j exp(-2*pi*i*R_j*k)) / sum_j |z_j|: 1 for a perfect fit.
    The real part, not the modulus: the reference fixes the absolute phase, and
    with one channel the score is cos(measured - 2*pi*eps*k), the rule of
    :func:`hitops.calibrate.offsets.choose_offset`.
    One channel cannot tell k from k + 43 at R = 230/86; across a band the
    offsets of a wrong k change with frequency as a delay of k/nu_ref, so a
    candidate far from the truth decorrelates over the channels.
    """
    n_k = candidates.shape[0]
    scores = np.zeros(n_k)
    total = 0.0
    for j in range(chan_sums.shape[0]):
        total += abs(chan_sums[j])
    if total == 0.0:
        return scores
    for i in range(n_k):
        acc = 0j
        for j in range(chan_sums.shape[0]):
            # the fractional turns of R_j*k only: exact for |k| up to ~1e6
            turns = ratios[j] * candidates[i]
            turn = -TWO_PI * (turns - math.floor(turns))
            acc += chan_sums[j] * complex(math.cos(turn), math.sin(turn))
        scores[i] = acc.real / total
    return scores


@numba.njit(cache=True, nogil=True)
def rotate_channels(data, phasor, delay, chan_offset):
    """Target rows times a phasor at the window's reference channel and a delay across it.

    data: (n_row, n_chan, n_corr) complex; phasor: (n_row, n_corr) complex, the
    correction at frequency nu_0 (zero where not calibrated); delay: (n_row,
    n_corr) seconds; chan_offset: (n_chan,) nu_k - nu_0 in Hz.  Returns
    data * phasor * exp(-2*pi*i*(nu_k - nu_0)*delay) as complex64.  This is the
    per-channel transfer written the way a CASA 'Fringe Jones' table holds it: with
    phasor = exp(-i*R_0*psi) and delay = psi / (2*pi*nu_ref), channel k gets
    exp(-i*R_k*psi) (issue 26: per-channel ratios on one reference phase are a
    phase plus a delay).
    """
    n_row, n_chan, n_corr = data.shape
    out = np.zeros((n_row, n_chan, n_corr), dtype=np.complex64)
    even = evenly_spaced(chan_offset)
    step_hz = (chan_offset[n_chan - 1] - chan_offset[0]) / max(n_chan - 1, 1)
    for r in range(n_row):
        for c in range(n_corr):
            p = complex(phasor[r, c])
            if p == 0j:
                continue
            rotate_sample(out, data, r, c, p, delay[r, c], chan_offset, even, step_hz)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def rotate_sample(out, data, r, c, phasor, tau, chan_offset, even, step_hz):
    """``out[r, :, c]`` = ``data[r, :, c]`` * phasor * exp(-2*pi*i*(nu_k - nu_0)*tau): the
    rotation of one sample's channels, a phasor stepped by the delay's per-channel turn
    on evenly spaced channels (``even``, ``step_hz``), evaluated per channel otherwise.
    Writes only ``out``, the caller's own output array."""
    rotor = phasor * cis(-TWO_PI * chan_offset[0] * tau)
    step = cis(-TWO_PI * step_hz * tau)
    for k in range(chan_offset.shape[0]):
        if not even:
            rotor = phasor * cis(-TWO_PI * chan_offset[k] * tau)
        out[r, k, c] = data[r, k, c] * rotor
        rotor *= step


@numba.njit(cache=True, nogil=True)
def cell_delays(calibrated, ref_phase, ref_wraps, offset_k, scan_of_time, nu_ref, unwrap):
    """The delay psi / (2*pi*nu_ref), seconds, of every calibrated (baseline, time) cell.

    calibrated: (n_bl, n_time, n_corr) bool; ref_phase, ref_wraps: (n_bl, n_corr,
    n_time) the tracked reference phase and its wrap counts; offset_k: (n_bl, n_corr,
    n_scan) int64, the n0 step's integers per scan (zeros without it); unwrap: psi =
    phi - 2*pi*(n + k) (PWC, CWU) or the wrapped phi itself (CFPT).  With
    :func:`rotate_channels` this gives channel k the phase -R_k*psi.
    Returns (n_bl, n_time, n_corr) float64, 0 where not calibrated.
    """
    n_bl, n_time, n_corr = calibrated.shape
    out = np.zeros((n_bl, n_time, n_corr))
    scale = 1.0 / (TWO_PI * nu_ref)
    for b in range(n_bl):
        for t in range(n_time):
            s = scan_of_time[t]
            for c in range(n_corr):
                if not calibrated[b, t, c]:
                    continue
                psi = ref_phase[b, c, t]
                if unwrap:
                    psi -= TWO_PI * (ref_wraps[b, c, t] + offset_k[b, c, s])
                out[b, t, c] = psi * scale
    return out
