"""Wideband kernels against the physics of a non-dispersive troposphere (issue 26).

The truth comes from the path alone: every channel of either band sees
2*pi*nu_k*(L_p - L_q)/c, plus a constant instrumental delay per station in the
reference band.  The reference window is 16 x 125 MHz at 86 GHz, the target two
16 x 125 MHz windows centred at 227.1 and 229.1 GHz (GUIDE.md, "Wideband"), and
the path drifts by several centimetres over 20 minutes, so the 86-GHz phase
wraps many times.  Plausible wrong implementations (one ratio per window, no
wrap count, a plain average over unevenly flagged reference channels) are shown
to fail the same coherence checks.
"""

from __future__ import annotations

import math

import dask.array as da
import numpy as np
import pytest

from hitops.kernels import wideband
from hitops.tracking.count import count_wraps

C_LIGHT = 299_792_458.0
N_ANT, N_TIME = 5, 1200                      # 20 min at 1 s
REF_FREQ = 86.0e9
REF_CHANS = REF_FREQ + (np.arange(16) - 7.5) * 125e6
TGT_WINDOWS = [227.1e9 + (np.arange(16) - 7.5) * 125e6, 229.1e9 + (np.arange(16) - 7.5) * 125e6]
TGT_CHANS = np.concatenate(TGT_WINDOWS)


def paths(seed=3):
    """Excess path (m) of each station over time: smooth, a few cm, zero at the start."""
    rng = np.random.default_rng(seed)
    t = np.arange(N_TIME, dtype=float)
    out = np.zeros((N_ANT, N_TIME))
    for a in range(N_ANT):
        amp, period, phase = rng.uniform(0.02, 0.04), rng.uniform(500, 900), rng.uniform(0, 2 * np.pi)
        out[a] = amp * (np.sin(2 * np.pi * t / period + phase) - np.sin(phase))
    return out


def baselines():
    return [(p, q) for p in range(N_ANT) for q in range(p + 1, N_ANT)]


def visibilities(chan_freq, path, inst_delay=None):
    """Rows (baseline-major, then time) x channels x 1 correlation of a 1-Jy point source."""
    rows = []
    for p, q in baselines():
        dl = (path[p] - path[q])[:, None]                      # (n_time, 1)
        phase = 2 * np.pi * chan_freq[None, :] * dl / C_LIGHT
        if inst_delay is not None:
            phase = phase + 2 * np.pi * (chan_freq[None, :] - REF_FREQ) * (inst_delay[p] - inst_delay[q])
        rows.append(np.exp(1j * phase))
    return np.concatenate(rows)[:, :, None].astype(np.complex64)


def reduce_reference(ref, ok_ref):
    """The reference window reduced to 86.0 GHz by the delay fit."""
    return wideband.reference_phasors(ref, ok_ref, REF_CHANS, REF_FREQ,
                                      wideband.row_delays(ref, ok_ref, REF_CHANS))


def track(reduced, good):
    """Unwrapped reference phase of every row: one wrap count per baseline series."""
    phase = np.angle(reduced[:, 0]).reshape(len(baselines()), N_TIME)
    valid = good[:, 0].reshape(len(baselines()), N_TIME)
    wraps = np.stack([count_wraps(phase[b], valid[b]) for b in range(phase.shape[0])])
    return wideband.unwrapped_reference(phase, wraps).reshape(-1, 1), valid.reshape(-1, 1)


def channel_coherence(calibrated):
    """Whole-track coherence of every (baseline, channel): |mean of the unit phasors|."""
    n_bl = len(baselines())
    unit = calibrated[:, :, 0] / np.abs(calibrated[:, :, 0])
    return np.abs(unit.reshape(n_bl, N_TIME, -1).mean(axis=1))


@pytest.fixture(scope="module")
def scene():
    path = paths()
    inst = np.random.default_rng(5).uniform(-0.5e-9, 0.5e-9, N_ANT)   # +-0.5 ns in the reference band
    ref = visibilities(REF_CHANS, path, inst)
    tgt = visibilities(TGT_CHANS, path)
    return ref, tgt, path


def test_delay_fit_recovers_phase_and_delay_where_a_plain_average_does_not():
    tau, phi0 = 0.37e-9, 1.1
    vis = np.exp(1j * (phi0 + 2 * np.pi * (REF_CHANS - REF_FREQ) * tau))[None, :, None]
    ok = np.ones(vis.shape, bool)
    ok[0, :6, 0] = False                        # the lower six channels flagged
    vis_copy, ok_copy = vis.copy(), ok.copy()
    delay = wideband.row_delays(vis, ok, REF_CHANS)
    reduced, good = wideband.reference_phasors(vis, ok, REF_CHANS, REF_FREQ, delay)
    assert delay[0, 0] == pytest.approx(tau, abs=1e-15)
    assert good[0, 0] and abs(np.angle(reduced[0, 0] * np.exp(-1j * phi0))) < 1e-9
    assert abs(reduced[0, 0]) == pytest.approx(1.0, abs=1e-12)   # no decorrelation
    plain, _ = wideband.plain_average(vis, ok)
    # the plain average refers the phase to the usable channels' mean frequency (+375 MHz)
    # and loses amplitude across the slope
    assert abs(np.angle(plain[0, 0] * np.exp(-1j * phi0))) > 0.8
    assert abs(plain[0, 0]) < 0.8
    assert np.array_equal(vis, vis_copy) and np.array_equal(ok, ok_copy)   # inputs untouched


def test_rows_without_data_stay_unusable():
    vis = np.zeros((3, 16, 2), np.complex64)
    vis[1] = 1.0
    vis[2, 3, 0] = np.nan + 1j
    ok = np.ones(vis.shape, bool)
    ok[1, :, 1] = False
    delay = wideband.row_delays(vis, ok, REF_CHANS)
    reduced, good = wideband.reference_phasors(vis, ok, REF_CHANS, REF_FREQ, delay)
    assert good.tolist() == [[False, False], [True, False], [False, False]]
    assert np.isnan(delay[0]).all() and delay[1, 0] == 0.0


def test_per_channel_ratios_keep_every_target_channel_coherent(scene):
    ref, tgt, _ = scene
    ok_ref, ok_tgt = np.ones(ref.shape, bool), np.ones(tgt.shape, bool)
    reduced, good = reduce_reference(ref, ok_ref)
    unwrapped, valid = track(reduced, good)
    assert np.abs(np.diff(unwrapped[:, 0].reshape(-1, N_TIME), axis=1)).max() < np.pi
    assert (np.ptp(unwrapped[:, 0].reshape(-1, N_TIME), axis=1) > 6 * np.pi).all()  # many wraps
    out, calibrated = wideband.apply_channel_ratios(tgt, ok_tgt, unwrapped, valid, TGT_CHANS / REF_FREQ)
    assert calibrated.all()
    assert channel_coherence(out).min() > 0.99999
    assert np.abs(np.angle(out)).max() < 1e-3          # the path is gone from every channel


def test_one_ratio_per_window_and_no_wrap_count_fail_the_same_check(scene):
    ref, tgt, _ = scene
    ok_ref, ok_tgt = np.ones(ref.shape, bool), np.ones(tgt.shape, bool)
    reduced, good = reduce_reference(ref, ok_ref)
    unwrapped, valid = track(reduced, good)
    window_ratio = np.repeat([w.mean() / REF_FREQ for w in TGT_WINDOWS], 16)
    out, _ = wideband.apply_channel_ratios(tgt, ok_tgt, unwrapped, valid, window_ratio)
    per_window = channel_coherence(out)
    assert per_window.min() < 0.999                     # the window edges drift by radians
    assert per_window[:, [7, 8, 23, 24]].min() > 0.999   # near the centres it is fine
    wrapped = np.angle(reduced)                          # CFPT: no wrap count
    out, _ = wideband.apply_channel_ratios(tgt, ok_tgt, wrapped, good, TGT_CHANS / REF_FREQ)
    assert channel_coherence(out).max() < 0.9


@pytest.mark.parametrize("lower_half_flagged", [False, True])
def test_plain_average_fails_where_the_delay_fit_holds(scene, lower_half_flagged):
    # all channels: the stations' instrumental delays (up to 1 ns on a baseline across
    # 2 GHz) decorrelate the plain average to nothing on some rows, and wrap counting on
    # its phase fails; lower half flagged: its phase refers to 86.5 GHz, not 86.0
    ref, tgt, _ = scene
    ok_ref, ok_tgt = np.ones(ref.shape, bool), np.ones(tgt.shape, bool)
    if lower_half_flagged:
        ok_ref[:, :8, :] = False
    results = {}
    for name in ("delay fit", "plain"):
        if name == "plain":
            reduced, good = wideband.plain_average(ref, ok_ref)
        else:
            reduced, good = reduce_reference(ref, ok_ref)
        unwrapped, valid = track(reduced, good)
        out, _ = wideband.apply_channel_ratios(tgt, ok_tgt, unwrapped, valid, TGT_CHANS / REF_FREQ)
        results[name] = channel_coherence(out).min()
    assert results["delay fit"] > 0.99999
    assert results["plain"] < 0.99


def test_dask_wrappers_equal_the_kernels(scene):
    ref, tgt, _ = scene
    ok_ref, ok_tgt = np.ones(ref.shape, bool), np.ones(tgt.shape, bool)
    ok_ref[::7, 3, 0] = False
    delay = wideband.row_delays(ref, ok_ref, REF_CHANS)
    reduced, good = wideband.reference_phasors(ref, ok_ref, REF_CHANS, REF_FREQ, delay)
    lazy_reduced, lazy_good = wideband.reference_phasors_dask(
        da.from_array(ref, chunks=(1000, 4, 1)), da.from_array(ok_ref, chunks=(1000, 4, 1)),
        REF_CHANS, REF_FREQ)
    assert np.array_equal(lazy_reduced.compute(), reduced)
    assert np.array_equal(lazy_good.compute(), good)
    unwrapped, valid = track(reduced, good)
    out, _ = wideband.apply_channel_ratios(tgt, ok_tgt, unwrapped, valid, TGT_CHANS / REF_FREQ)
    lazy = wideband.apply_channel_ratios_dask(da.from_array(tgt, chunks=(777, 8, 1)),
                                              da.from_array(ok_tgt, chunks=(777, 8, 1)),
                                              unwrapped, valid, TGT_CHANS / REF_FREQ)
    assert np.array_equal(lazy.compute(), out)


def test_large_phases_keep_float64_precision():
    # 20 000 turns of unwrapped reference phase (a long, wet track): the product R_k*psi
    # must still give the right target phase to well under a milliradian
    turns = 20_000
    psi = np.array([[2 * np.pi * turns + 0.3]])
    ratio = np.array([229.1e9 / REF_FREQ])
    tgt = np.exp(1j * (ratio[0] * psi[0, 0]))[None, None, None] * np.ones((1, 1, 1), np.complex64)
    out, _ = wideband.apply_channel_ratios(tgt.astype(np.complex64), np.ones((1, 1, 1), bool),
                                           psi, np.ones((1, 1), bool), ratio)
    assert abs(math.atan2(out[0, 0, 0].imag, out[0, 0, 0].real)) < 1e-4


def test_a_band_of_channels_picks_n0_where_one_channel_cannot():
    # PWC counted from n'(t0) = 0 while the true count started at n0 = 57: each channel's
    # output is off by 2*pi*R_j*57; the reference (a model) is good to 2 degrees
    ks = np.arange(-200, 201, dtype=np.int64)
    n0 = 57
    ratios = TGT_CHANS / REF_FREQ
    z = np.exp(1j * (2 * np.pi * ((ratios * n0) % 1) + np.deg2rad(2.0)))
    scores = wideband.channel_offset_scores(z, ratios, ks)
    assert ks[np.argmax(scores)] == n0
    # the neighbours on the 8.37-degree grid (k = n0 +- 3) still need a good reference
    # (cos 8.4 deg = 0.99 on one channel, 0.92-0.94 across the band); far candidates,
    # which one channel cannot tell apart at all, lose their coherence across the band
    assert np.sort(scores)[-2] < 0.95
    assert scores[np.abs(ks - n0) > 3].max() < 0.8
    one = np.array([230e9 / REF_FREQ])                      # R = 230/86: k and k + 43 are one offset
    single = wideband.channel_offset_scores(np.exp(1j * 2 * np.pi * ((one * n0) % 1)), one, ks)
    tied = ks[single >= single.max() - 1e-9]
    assert n0 in tied and n0 - 43 in tied and n0 + 43 in tied


def test_the_channel_recurrence_equals_direct_evaluation():
    # evenly spaced channels are rotated by recurrence, others channel by channel: both
    # must give exp(-i*R_k*psi) to single precision, on a phase of thousands of radians
    rng = np.random.default_rng(7)
    psi = rng.uniform(-5000, 5000, (50, 2))
    valid = np.ones((50, 2), bool)
    for chans in (TGT_WINDOWS[0], TGT_CHANS):          # one window (even), two windows (not)
        ratios = chans / REF_FREQ
        tgt = np.ones((50, chans.size, 2), np.complex64)
        out, _ = wideband.apply_channel_ratios(tgt, np.ones(tgt.shape, bool), psi, valid, ratios)
        direct = np.exp(-1j * ratios[None, :, None] * psi[:, None, :])
        assert np.abs(out - direct).max() < 1e-6
    delay = rng.uniform(-1e-9, 1e-9, (50, 2))
    vis = np.exp(1j * 2 * np.pi * (REF_CHANS[None, :, None] - REF_FREQ) * delay[:, None, :])
    reduced, _ = wideband.reference_phasors(vis, np.ones(vis.shape, bool), REF_CHANS, REF_FREQ, delay)
    assert np.abs(reduced - 1).max() < 1e-12


def test_phase_plus_delay_is_the_per_channel_ratio(scene):
    # exp(-i*R_0*psi) at the window centre and a delay psi/(2*pi*nu_ref) across it give
    # every channel exp(-i*R_k*psi): the form a Fringe Jones table carries
    ref, tgt, _ = scene
    ok_ref = np.ones(ref.shape, bool)
    reduced, good = reduce_reference(ref, ok_ref)
    psi, valid = track(reduced, good)
    window = TGT_WINDOWS[1]
    centre = window.mean()
    window_vis = tgt[:, 16:, :]
    direct, _ = wideband.apply_channel_ratios(window_vis, np.ones(window_vis.shape, bool), psi,
                                              valid, window / REF_FREQ)
    phasor = np.exp(-1j * (centre / REF_FREQ) * psi)
    rotated = wideband.rotate_channels(window_vis, phasor, psi / (2 * np.pi * REF_FREQ), window - centre)
    assert np.abs(rotated - direct).max() < 1e-5
    # the delay left out (one ratio per window) is what fails
    flat = wideband.rotate_channels(window_vis, phasor, np.zeros_like(psi), window - centre)
    assert np.abs(np.angle(flat)).max() > 0.5
