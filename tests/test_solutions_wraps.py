"""hitops.solutions.wraps: wrap counting on solution series, rate bridging, re-referencing.

The truth is a known smooth phase per antenna (radians at the reference frequency);
the kernel sees only what a calibration table holds: the phase wrapped to [-pi, pi),
referred to the table's reference antenna, and the phase rate.
"""

from __future__ import annotations

import numpy as np

from hitops.solutions.wraps import (BRIDGED, NO_SWITCH, PREDICT_NONE, PREDICT_RATES, PREDICT_SLOPE,
                                    segment_starts, unwrap_solutions)


def _wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


def _truth(n_sol, n_ant, dt, seed, speed):
    """Smooth antenna phases (rad) and their exact rates (rad/s); antenna 0 included."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_sol) * dt
    phase = np.zeros((n_sol, n_ant))
    rate = np.zeros((n_sol, n_ant))
    for a in range(n_ant):
        for period in (900.0, 300.0, 120.0):
            amp, start = speed * period * rng.normal() / (2 * np.pi), rng.uniform(0, 2 * np.pi)
            phase[:, a] += amp * np.sin(2 * np.pi * t / period + start)
            rate[:, a] += amp * 2 * np.pi / period * np.cos(2 * np.pi * t / period + start)
    return t, phase, rate


def _run(wrapped, valid, t, rate, refant, starts=None, predict=PREDICT_RATES):
    starts = np.zeros(t.size, bool) if starts is None else starts
    return unwrap_solutions(wrapped, valid, t, rate, refant, starts, predict)


def _baseline_errors(unwrapped, truth):
    """(u_p - u_q) - (truth_p - truth_q) for every pair: constant in time when counted right."""
    n_ant = truth.shape[1]
    return [(unwrapped[:, p] - unwrapped[:, q]) - (truth[:, p] - truth[:, q])
            for p in range(n_ant) for q in range(p + 1, n_ant)]


def test_rates_bridge_steps_larger_than_pi():
    # 4-s solutions whose phase moves by up to ~3 rad per step between solutions
    t, truth, rate = _truth(600, 4, 4.0, seed=2, speed=0.7)
    truth -= truth[:, :1]
    rate -= rate[:, :1]
    steps = np.abs(np.diff(truth, axis=0))
    assert steps.max() > np.pi                    # plain step counting must fail here
    wrapped = _wrap(truth)
    valid = np.ones(truth.shape, bool)
    refant = np.zeros(t.size, np.int64)
    unwrapped, wraps, offset, residual, switch = _run(wrapped, valid, t, rate, refant)
    for err in _baseline_errors(unwrapped, truth):
        assert np.ptp(err) < 1e-9
    assert np.nanmax(np.abs(residual)) < 1.0
    np.testing.assert_allclose(unwrapped, wrapped + offset[:, None] + 2 * np.pi * wraps)
    assert wraps.dtype == np.int64 and unwrapped.dtype == np.float64
    # without the rates (the paper's step counter) the same series is miscounted
    plain = _run(wrapped, valid, t, rate, refant, predict=PREDICT_NONE)[0]
    assert max(np.ptp(err) for err in _baseline_errors(plain, truth)) > 6.0


def test_inputs_are_not_mutated_and_flags_are_skipped():
    t, truth, rate = _truth(300, 3, 4.0, seed=5, speed=0.3)
    truth -= truth[:, :1]
    rate -= rate[:, :1]
    wrapped = _wrap(truth)
    valid = np.ones(truth.shape, bool)
    valid[100:106, 2] = False                      # a flagged stretch: bridged by the rates
    wrapped[100:106, 2] = 123.0                    # what is flagged is never read
    copies = [x.copy() for x in (wrapped, valid, t, rate)]
    unwrapped = _run(wrapped, valid, t, rate, np.zeros(t.size, np.int64))[0]
    for before, after in zip(copies, (wrapped, valid, t, rate)):
        np.testing.assert_array_equal(before, after)
    assert np.isnan(unwrapped[100:106, 2]).all()
    err = (unwrapped[:, 2] - unwrapped[:, 1]) - (truth[:, 2] - truth[:, 1])
    assert np.nanmax(err) - np.nanmin(err) < 1e-9


def test_reference_antenna_change_is_re_referred():
    # refant 0 for the first half; antenna 0 then sets and the table refers to antenna 1.
    # The frame jump at the switch (antenna 1's phase in antenna 0's frame) is put at pi and
    # the solutions carry 0.03 rad of noise: counted antenna by antenna, the jump rounds up
    # on some and down on others; re-referred, every antenna sees the same jump.
    t, truth, rate = _truth(400, 6, 4.0, seed=11, speed=0.4)
    half = 200
    valid = np.ones(truth.shape, bool)
    valid[half:, 0] = False
    refant = np.where(np.arange(t.size) < half, 0, 1)

    def table(truth, noise):
        frame = np.where(refant[:, None] == 0, truth[:, :1], truth[:, 1:2])
        frame_rate = np.where(refant[:, None] == 0, rate[:, :1], rate[:, 1:2])
        wrapped = _wrap(truth - frame + noise)
        wrapped[:half, 0] = 0.0                     # the reference antenna's own solution
        wrapped[half:, 1] = 0.0
        return wrapped, rate - frame_rate

    # where the antenna-by-antenna count meets the switch: shift antenna 1 to put it at pi
    wrapped, table_rate = table(truth, 0.0)
    jump = _run(wrapped, valid, t, table_rate, np.full(t.size, -1))[3][half, 2]
    truth[:, 1] += jump - np.pi
    wrapped, table_rate = table(truth, np.random.default_rng(4).normal(0.0, 0.03, truth.shape))
    unwrapped, wraps, offset, residual, switch = _run(wrapped, valid, t, table_rate, refant)
    assert switch[half] == BRIDGED and (switch[np.arange(t.size) != half] == NO_SWITCH).all()
    pairs = [(p, q) for p in range(1, 6) for q in range(p + 1, 6)]
    for p, q in pairs:
        err = (unwrapped[:, p] - unwrapped[:, q]) - (truth[:, p] - truth[:, q])
        assert np.ptp(err) < 0.5, (p, q)
    # the same table counted without knowing of the switch (a plausible wrong implementation)
    naive = _run(wrapped, valid, t, table_rate, np.full(t.size, -1))[0]
    worst = max(np.ptp((naive[:, p] - naive[:, q]) - (truth[:, p] - truth[:, q])) for p, q in pairs)
    assert worst > 6.0


def test_segments_start_at_scans_and_gaps():
    times = np.array([0.0, 4.0, 8.0, 100.0, 104.0, 108.0, 112.0])
    scan = np.array([1, 1, 1, 1, 1, 2, 2])
    np.testing.assert_array_equal(segment_starts(times, scan, max_gap=60.0),
                                  [True, False, False, True, False, True, False])


def test_per_channel_transfer_is_pwc_per_channel():
    """R_k*(phi + 2*pi*n) is PWC's correction R_k*phi + 2*pi*eps_k*n mod 2*pi, channel by channel.

    (n counted as here, u = phi + 2*pi*n; the paper's n has the other sign, unwrap = x - 2*pi*n.)
    """
    from hitops.solutions.transfer import channel_phases

    t, truth, rate = _truth(300, 3, 4.0, seed=8, speed=0.3)
    truth -= truth[:, :1]
    rate -= rate[:, :1]
    wrapped = _wrap(truth)
    unwrapped, wraps, offset, _, _ = _run(wrapped, np.ones(truth.shape, bool), t, rate,
                                          np.zeros(t.size, np.int64))
    assert np.abs(wraps).max() >= 3 and not offset.any()
    nu_ref = 86.0e9
    chan = 226.1625e9 + 125e6 * np.arange(16)
    ratio = chan / nu_ref
    eps = ratio - np.floor(ratio)
    ours = channel_phases(unwrapped, nu_ref, chan)
    pwc = ratio * wrapped[..., None] + 2 * np.pi * eps * wraps[..., None]
    np.testing.assert_allclose(np.angle(np.exp(1j * (ours - pwc))), 0.0, atol=1e-9)
    # and it is the truth scaled per channel, up to a constant per antenna
    err = np.angle(np.exp(1j * (ours - ratio * truth[..., None])))
    assert np.ptp(err, axis=0).max() < 1e-9


def test_series_without_rates_are_bridged_by_their_slope():
    # 4-s solutions whose phase moves by up to 2.4 rad per step, a 12-s gap in one antenna
    # where it moves fast: the last two solutions' slope predicts well; the step counter fails
    t, truth, rate = _truth(600, 4, 4.0, seed=4, speed=0.1)
    truth -= truth[:, :1]
    steps = np.abs(np.diff(truth, axis=0))
    assert np.pi > steps.max() > 2.0
    valid = np.ones(truth.shape, bool)
    valid[300:302, 2] = False
    zero = np.zeros_like(truth)
    refant = np.zeros(t.size, np.int64)
    slope, _, _, residual, _ = _run(_wrap(truth), valid, t, zero, refant, predict=PREDICT_SLOPE)
    assert all(np.nanmax(err) - np.nanmin(err) < 1e-9 for err in _baseline_errors(slope, truth))
    assert np.nanmax(np.abs(residual[2:])) < 1.0      # the first step has no slope yet
    plain = _run(_wrap(truth), valid, t, zero, refant, predict=PREDICT_NONE)[0]
    assert max(np.nanmax(err) - np.nanmin(err) for err in _baseline_errors(plain, truth)) > 6.0
