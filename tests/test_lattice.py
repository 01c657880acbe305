"""The integer lattice solve of the antenna n0 offsets (hitops.calibrate.n0.lattice), alone.

Edges carry z_e = sum exp(i (Phi_model - Phi_out)); a node's count error k_v moves
its baselines' outputs by 2 pi eps (k_a - k_b), so the edge of a noiseless scene
is n_e exp(i 2 pi eps (k_a - k_b)) and the solve must return j = k (mod the
lattice period: 43 for eps = 29/43) relative to the gauge.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hitops.calibrate.n0.lattice import candidates, solve_lattice
from hitops.kernels.segments import segment_run_sums

EPS = 230.0 / 86.0 - 2           # 29/43


def scene(rng, n_ant, noise=0.0, n=300, spread=21):
    truth = rng.integers(-spread, spread + 1, n_ant)
    truth[0] = 0
    a, b = np.triu_indices(n_ant, 1)
    out = -2 * np.pi * EPS * (truth[a] - truth[b])
    z = np.array([np.sum(np.exp(-1j * (out[e] + rng.normal(0, noise, n)))) if noise else
                  n * np.exp(-1j * out[e]) for e in range(a.size)])
    return truth, a, b, z, np.full(a.size, n)


def same_point(j, k):
    return np.all(np.abs(np.angle(np.exp(2j * np.pi * EPS * (np.asarray(j) - k)))) < 1e-6)


def test_candidates_are_the_distinct_lattice_points_smallest_k_first():
    ks, ph = candidates(EPS, 50)
    assert ks.size == 43 and ks[0] == 0 and np.max(np.abs(ks)) == 21
    angles = np.sort(np.degrees(np.angle(ph)) % 360)
    assert np.allclose(np.diff(angles), 360 / 43, atol=1e-6)      # the 8.37 deg grid
    assert candidates(EPS, 3)[0].tolist() == [0, -1, 1, -2, 2, -3, 3]
    assert candidates(0.5, 10)[0].tolist() == [0, -1]                # R = 2.5: 0 and 180 deg


@pytest.mark.parametrize("n_ant", [2, 3, 4, 5, 8])
def test_noiseless_scenes_give_the_true_integers(n_ant):
    rng = np.random.default_rng(n_ant)
    for _ in range(5):
        truth, a, b, z, n = scene(rng, n_ant)
        a_in, z_in = a.copy(), z.copy()
        sol = solve_lattice(n_ant, a, b, z, n, EPS, 50, gauge_order=[0])
        assert np.array_equal(a, a_in) and np.array_equal(z, z_in)       # pure
        assert sol.k[0] == 0 and sol.gauge.tolist() == [0]
        assert same_point(sol.k, truth) and np.all(np.abs(sol.k) <= 21)
        assert sol.method == ("trivial" if n_ant == 1 else
                              "exhaustive" if 43 ** (n_ant - 1) <= 250_000 else "descent")
        assert sol.score == pytest.approx(sol.samples, rel=1e-9)      # every edge aligned
        assert np.allclose(np.angle(sol.edge_sum), 0, atol=1e-9)


def test_descent_finds_the_exhaustive_optimum_where_the_data_decide():
    rng = np.random.default_rng(7)
    agree = 0
    for _ in range(40):
        truth, a, b, z, n = scene(rng, 4, noise=1.5, n=300)
        full = solve_lattice(4, a, b, z, n, EPS, 50, gauge_order=[0])
        descent = solve_lattice(4, a, b, z, n, EPS, 50, gauge_order=[0], exhaustive_limit=0)
        assert descent.method == "descent" and full.method == "exhaustive"
        assert descent.score <= full.score + 1e-9
        agree += abs(descent.score - full.score) < 1e-9
    assert agree >= 36


def test_gauge_components_and_bounds():
    # two antennas' segments (nodes 0-1, 2-3 of antennas p, q) joined through a third
    # antenna (node 4): one component; node 5 is alone (its own gauge, k = 0)
    k_true = np.array([0, 5, -3, 7, 2, 0])
    a = np.array([0, 1, 2, 3])
    b = np.array([4, 4, 4, 4])
    z = 100 * np.exp(-1j * 2 * np.pi * EPS * -(k_true[a] - k_true[b]))
    sol = solve_lattice(6, a, b, z, np.full(4, 100), EPS, 50, gauge_order=[4])
    assert sol.gauge.tolist() == [4, 5] and sol.k[4] == 0 and sol.k[5] == 0
    assert same_point(sol.k[:4] - sol.k[4], k_true[:4] - k_true[4])
    # the gauge defaults to the node with the most samples
    sol = solve_lattice(6, a, b, z, np.array([10, 10, 10, 10]), EPS, 50)
    assert sol.gauge[0] == 4
    # |k| <= max_k: with max_k = 0 nothing moves
    sol = solve_lattice(6, a, b, z, np.full(4, 100), EPS, 0, gauge_order=[4])
    assert np.all(sol.k == 0)
    with pytest.raises(ValueError):
        solve_lattice(2, [0], [0], [1 + 0j], [1], EPS, 5)


def test_segment_run_sums_match_a_direct_sum():
    rng = np.random.default_rng(3)
    n_bl, n_corr, n_time = 3, 2, 50
    keys = np.repeat(rng.integers(0, 3, (n_bl, n_corr, 5)), 10, axis=2)
    keys[0, 0, :7] = -1
    tgt = rng.uniform(-np.pi, np.pi, (n_bl, n_corr, n_time))
    off = rng.uniform(-np.pi, np.pi, (n_bl, n_corr, n_time))
    phasor = np.exp(1j * rng.uniform(-np.pi, np.pi, (n_bl, n_time, n_corr))).astype(np.complex64)
    cal = rng.random((n_bl, n_time, n_corr)) > 0.2
    ok = rng.random((n_bl, n_corr, n_time)) > 0.1
    index, sums, counts = segment_run_sums(keys, tgt, phasor, cal, off, ok)
    expected = {}
    for b in range(n_bl):
        for c in range(n_corr):
            for t in range(n_time):
                if keys[b, c, t] >= 0 and cal[b, t, c] and ok[b, c, t]:
                    d = off[b, c, t] - (tgt[b, c, t] + np.angle(phasor[b, t, c]))
                    e = expected.setdefault((b, c, keys[b, c, t]), [0j, 0])
                    e[0] += np.exp(1j * d)
                    e[1] += 1
    assert [tuple(r) for r in index.tolist()] == sorted(expected)
    for (b, c, key), z, cnt in zip(index.tolist(), sums, counts):
        assert z == pytest.approx(expected[(b, c, key)][0], abs=1e-5)   # complex64 phasors
        assert cnt == expected[(b, c, key)][1]


def test_apply_segment_offsets_adds_k_on_its_segment_only():
    from hitops.tracking.state import apply_segment_offsets

    keys = np.array([[[5, 5, 7, 7, -1, 9]]], np.int64)
    counts = np.zeros_like(keys)
    out = apply_segment_offsets(counts, keys, {(0, 0, 7): 3, (0, 0, 9): -2, (0, 0, 5): 0})
    assert out.tolist() == [[[0, 0, 3, 3, 0, -2]]]
    assert counts.tolist() == [[[0, 0, 0, 0, 0, 0]]]
    assert apply_segment_offsets(counts, keys, {}) is counts


def test_uniqueness_against_the_per_node_phase_error():
    """Where the per-node phase error of the sums stays well inside half the lattice
    spacing (4.19 deg) the solve is right in every trial (docs/calibrate.md)."""
    rng = np.random.default_rng(11)
    spacing = 360 / 43
    for n_ant, noise, n in ((8, 1.0, 600), (4, 0.8, 600), (3, 0.6, 600)):
        # circular standard error of a node's measured offset: its n (n_ant - 1) samples
        # of wrapped-normal noise (rho_1 = exp(-s^2 / 2), rho_2 = exp(-2 s^2))
        r1, r2 = math.exp(-noise ** 2 / 2), math.exp(-2 * noise ** 2)
        node_err = math.degrees(math.sqrt((1 - r2) / (2 * n * (n_ant - 1) * r1 ** 2)))
        assert node_err < spacing / 2 / 3
        for _ in range(10):
            truth, a, b, z, cnt = scene(rng, n_ant, noise=noise, n=n)
            sol = solve_lattice(n_ant, a, b, z, cnt, EPS, 50, gauge_order=[0])
            assert same_point(sol.k, truth)


def test_segment_row_sums_equal_the_grid_form():
    """The driver's sums (row arrays through the row grid) equal the groups' (phase grids)."""
    from hitops.kernels.segments import segment_row_sums
    from hitops.kernels import fpt

    rng = np.random.default_rng(5)
    n_bl, n_corr, n_time = 3, 2, 40
    rows = rng.permutation(n_bl * n_time).reshape(n_bl, n_time)
    rows[1, 5:9] = -1
    n_row = n_bl * n_time
    keys = np.repeat(rng.integers(0, 3, (n_bl, n_corr, 4)), 10, axis=2)
    vis = (rng.normal(size=(n_row, n_corr)) + 1j * rng.normal(size=(n_row, n_corr))).astype(np.complex64)
    off = np.exp(1j * rng.uniform(-3, 3, (n_row, n_corr))).astype(np.complex64)
    ok = rng.random((n_row, n_corr)) > 0.1
    phasor_rows = np.exp(1j * rng.uniform(-3, 3, (n_row, n_corr))).astype(np.complex64)
    cal_rows = rng.random((n_row, n_corr)) > 0.2
    index, sums, counts = segment_row_sums(rows, keys, vis, phasor_rows, cal_rows, off, ok)
    # the same on grids
    safe = np.where(rows >= 0, rows, 0)
    tgt = np.angle(vis[safe]).transpose(0, 2, 1).astype(np.float64)
    offp = np.angle(off[safe]).transpose(0, 2, 1).astype(np.float64)
    offok = (ok[safe] & (rows >= 0)[:, :, None]).transpose(0, 2, 1)
    phasor = phasor_rows[safe]
    cal = cal_rows[safe] & (rows >= 0)[:, :, None]
    index2, sums2, counts2 = segment_run_sums(keys, tgt, phasor, cal, offp, offok)
    assert np.array_equal(index, index2) and np.array_equal(counts, counts2)
    assert np.allclose(sums, sums2, atol=1e-4)
