"""The numba kernels on their own: wrap counting, FPT phasors, offset choice."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hitops.calibrate.n0.baseline import choose_offset
from hitops.kernels import fpt
from hitops.tracking.count import Carry, count_scans, count_wraps


def wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def test_count_wraps_follows_the_papers_sign_convention():
    # rising phase crosses +pi -> lands near -pi: the wrapped series jumps down, n falls;
    # crossing from the -pi side (jump up) raises n
    true = np.concatenate([np.linspace(0, 3 * np.pi, 40), np.linspace(3 * np.pi, -2 * np.pi, 60)])
    wrapped = wrap(true)
    n = count_wraps(wrapped, np.ones(true.size, bool))
    expected = np.rint((wrapped - true) / (2 * np.pi)).astype(np.int64)
    assert n.dtype == np.int64
    assert np.array_equal(n, expected - expected[0])
    assert n.max() >= 1 and n.min() <= -1   # both directions were exercised


def test_count_wraps_skips_invalid_and_nan_and_does_not_mutate():
    rng = np.random.default_rng(0)
    true = np.cumsum(rng.normal(0.2, 0.3, 500))
    wrapped = wrap(true)
    valid = rng.random(500) > 0.2
    wrapped_bad = wrapped.copy()
    wrapped_bad[~valid] = rng.uniform(-np.pi, np.pi, int((~valid).sum()))  # junk where invalid
    wrapped_bad[5] = np.nan
    valid_copy, phase_copy = valid.copy(), wrapped_bad.copy()
    n = count_wraps(wrapped_bad, valid)
    assert np.array_equal(valid, valid_copy) and np.array_equal(wrapped_bad, phase_copy, equal_nan=True)
    truth = np.rint((wrapped - true) / (2 * np.pi)).astype(np.int64)
    ok = valid.copy()
    ok[5] = False
    first = np.flatnonzero(ok)[0]
    assert np.array_equal(n[ok], truth[ok] - truth[first])
    # invalid samples carry the previous count
    for t in np.flatnonzero(~ok):
        assert n[t] == (n[t - 1] if t else 0)


def test_count_wraps_edge_cases():
    assert count_wraps(np.zeros(0), np.zeros(0, bool)).size == 0
    assert np.array_equal(count_wraps(np.array([3.0]), np.array([True])), [0])
    assert np.array_equal(count_wraps(np.array([3.0, -3.0, 3.0]), np.zeros(3, bool)), [0, 0, 0])
    # exactly pi is not a wrap; just above is
    assert np.array_equal(count_wraps(np.array([0.0, math.pi]), np.ones(2, bool)), [0, 0])
    assert np.array_equal(count_wraps(np.array([-3.0, 3.0, -3.0]), np.ones(3, bool)), [0, 1, 0])


def test_track_carries_across_chunks_and_restarts_per_scan():
    rng = np.random.default_rng(2)
    n_time = 400
    true = np.cumsum(rng.normal(0.15, 0.3, (2, 3, n_time)), axis=2)
    phase = wrap(true)
    valid = rng.random(phase.shape) > 0.1
    scan = np.repeat([0, 1], n_time // 2)
    whole, _ = count_scans(phase, valid, scan, Carry.empty(2, 3))
    carry = Carry.empty(2, 3)
    parts = []
    for a, b in [(0, 57), (57, 200), (200, 201), (201, 400)]:
        w, carry = count_scans(phase[..., a:b], valid[..., a:b], scan[a:b], carry)
        parts.append(w)
    assert np.array_equal(np.concatenate(parts, axis=2), whole)
    # scan 1 starts again at 0 (its first valid sample has count 0)
    for b in range(2):
        for c in range(3):
            first = 200 + np.flatnonzero(valid[b, c, 200:])[0]
            assert whole[b, c, first] == 0


def test_transfer_phasors_match_the_formulas():
    rng = np.random.default_rng(3)
    n_bl, n_corr, n_time = 2, 2, 50
    ref_true = np.cumsum(rng.normal(0.3, 0.2, (n_bl, n_corr, n_time)), axis=2)
    ref = wrap(ref_true)
    tgt = wrap(rng.uniform(-10, 10, ref.shape))
    valid = np.ones(ref.shape, bool)
    valid[0, 1, 7] = False
    rows = np.arange(n_bl * n_time).reshape(n_bl, n_time)
    n_ref = np.stack([[count_wraps(ref[b, c], valid[b, c]) for c in range(n_corr)] for b in range(n_bl)])
    n_tgt = np.stack([[count_wraps(tgt[b, c], valid[b, c]) for c in range(n_corr)] for b in range(n_bl)])
    ratio, eps = 230 / 86, 230 / 86 - 2
    offsets = rng.uniform(-1, 1, (n_bl, n_corr, 1))
    scan = np.zeros(n_time, np.int64)
    out = {}
    for name, code in fpt.METHOD_CODES.items():
        p, cal = fpt.transfer_phasors(rows, tgt, valid, ref, valid, n_ref, n_tgt, ratio, eps, code,
                                      offsets, scan)
        assert p.shape == (n_bl, n_time, n_corr) and np.array_equal(cal, valid.transpose(0, 2, 1))
        assert p[0, 7, 1] == 0
        out[name] = wrap(tgt.transpose(0, 2, 1) + np.angle(p))
    pwc = wrap(tgt - ratio * ref + 2 * np.pi * eps * n_ref + offsets).transpose(0, 2, 1)
    cfpt = wrap(tgt - ratio * ref).transpose(0, 2, 1)
    ok = valid.transpose(0, 2, 1)
    assert np.allclose(wrap(out["pwc"] - pwc)[ok], 0, atol=1e-5)
    assert np.allclose(wrap(out["cfpt"] - cfpt)[ok], 0, atol=1e-5)
    # CWU unwraps both bands; rewrapping cancels the target unwrap: CWU == PWC
    assert np.allclose(wrap(out["cwu"] - out["pwc"])[ok], 0, atol=1e-5)


def test_gather_phase_conjugates_swapped_rows_and_exchanges_hands():
    vis = np.array([[1j, 1 + 0j, -1 + 0j, 1 + 1j]], np.complex64)   # RR RL LR LL
    ok = np.ones((1, 4), bool)
    rows = np.array([[0]])
    corr_map = np.array([[0, 1, 2, 3], [0, 2, 1, 3]])
    ph, va = fpt.gather_phase(rows, vis, ok, np.array([True]), corr_map)
    assert np.allclose(ph[0, :, 0], [-np.pi / 2, -np.pi, 0.0, -np.pi / 4])
    ph, va = fpt.gather_phase(rows, np.array([[0, np.nan, 1, 1]], np.complex64), ok,
                              np.array([False]), corr_map)
    assert va[0, :, 0].tolist() == [False, False, True, True] and np.isnan(ph[0, 0, 0])


def test_gather_phase_is_the_float64_argument_of_the_stored_value():
    """Each phase is the argument of the complex64 value as stored, to float64 rounding
    (the conjugate's for swapped rows, signed zeros and the -pi/pi edge included): an
    arctangent taken in float32, which numba picks for a complex64's parts, is 1e-7 rad
    off, ~10^9 float64 steps at pi."""
    rng = np.random.default_rng(4)
    n_row = 4000
    vis = (rng.normal(size=(n_row, 2)) + 1j * rng.normal(size=(n_row, 2))).astype(np.complex64)
    vis[:4, 0] = [complex(-1, 0.0), complex(-1, -0.0), complex(-2, 1e-38), complex(0.0, -3)]
    swapped = rng.random(n_row) < 0.5
    swapped[:4] = [False, True, True, False]
    rows = np.arange(n_row, dtype=np.int64).reshape(2, -1)
    identity = np.array([[0, 1], [0, 1]])
    ph, va = fpt.gather_phase(rows, vis, np.ones((n_row, 2), bool), swapped, identity)
    exact = np.angle(np.where(swapped[:, None], np.conj(vis.astype(np.complex128)),
                              vis.astype(np.complex128)))
    got = ph.transpose(0, 2, 1).reshape(n_row, 2)
    assert va.all()
    # within a float64 step or two of pi (NumPy's vector arctangent against its own loop)
    np.testing.assert_allclose(got, exact, rtol=0, atol=4 * np.spacing(np.pi))
    # -1 + 0j is pi; swapped, -1 - 0j is conjugated to -1 + 0j: pi again; -2 + tiny j
    # swapped is just below -pi's side: -pi
    assert got[:4, 0].tolist() == [np.pi, np.pi, -np.pi, -np.pi / 2]


def test_choose_offset_picks_bounded_k_and_flags_ambiguity():
    eps = 29 / 43
    for k in (-3, 0, 2, 7):
        z = 50 * np.exp(1j * 2 * np.pi * eps * k)
        choice = choose_offset(z, 50, eps, 10, 2.0)
        assert choice.k == k and choice.residual_deg < 1e-6 and not choice.ambiguous
        assert choice.runner_up_residual_deg == pytest.approx(360 / 43, abs=1e-6)
    # halfway between two candidates 8.37 deg apart: ambiguous
    half = np.exp(1j * (2 * np.pi * eps * 1 + np.radians(360 / 43 / 2)))
    assert choose_offset(half, 1, eps, 10, 2.0).ambiguous
    # a bound of 0 forces k = 0; no samples -> None
    assert choose_offset(np.exp(1j * 2), 1, eps, 0, 2.0).k == 0
    assert choose_offset(0j, 0, eps, 10, 2.0) is None
    # |k| <= 50 spans every lobe of eps = 29/43: k and k +- 43 are the same offset modulo
    # 2*pi (up to rounding); the smallest |k| is reported
    for k in (0, 3, -5):
        c = choose_offset(np.exp(1j * 2 * np.pi * eps * k), 1, eps, 50, 2.0)
        assert c.k == k and not c.ambiguous
    # eps = 1/2: k = 0 and k = 2 are the same offset; the smaller |k| wins, not ambiguous
    c = choose_offset(1 + 0j, 1, 0.5, 4, 2.0)
    assert c.k == 0 and not c.ambiguous and c.runner_up_residual_deg == pytest.approx(180)
