"""Antenna-based wrap tracking (issue 6): solve, transfer, closure phases, MS round trip."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hitops.errors import InputError
from hitops.tracking.antenna_kernel import closure_phases, solve_antenna_phases
from hitops.testing.slips import count_slips, slip_errors
from hitops.simulate.troposphere import fbm_circulant
from hitops.tracking import theory
from hitops.tracking.grid import grid_positions
from hitops.tracking.modes import track_antennas, track_series

TWO_PI = 2.0 * np.pi
RATIO = 230.0 / 86.0
EPS = RATIO - np.floor(RATIO)


def scene(n_time=6000, n_ant=4, starts=(0, 0, 0, 2000), rho=5.0, coherence_s=33.0, seed=1):
    """Antenna tropospheric phases (zero at each antenna's first sample, as in the paper),
    baseline reference visibilities with noise at per-sample SNR ``rho``, and target phases."""
    rng = np.random.default_rng(seed)
    trop = fbm_circulant(n_time, n_ant, 5.0 / 6.0, rng) * theory.kolmogorov_step_sigma(1.0, coherence_s)
    up = np.zeros((n_ant, n_time), bool)
    for p, s in enumerate(starts):
        trop[p] -= trop[p, s]
        up[p, s:] = True
    pairs = list(itertools.combinations(range(n_ant), 2))
    ant1 = np.array([p for p, _ in pairs], np.int64)
    ant2 = np.array([q for _, q in pairs], np.int64)
    true_bl = trop[ant1] - trop[ant2]
    valid = up[ant1] & up[ant2]
    noise = (rng.standard_normal(true_bl.shape) + 1j * rng.standard_normal(true_bl.shape)) / rho
    ref_vis = np.where(valid, np.exp(1j * true_bl) + noise, 0)
    target_noise = 0.05 * rng.standard_normal(true_bl.shape)
    target_phase = RATIO * true_bl + target_noise
    return dict(trop=trop, ant1=ant1, ant2=ant2, true_bl=true_bl, valid=valid, ref_vis=ref_vis,
                target_phase=target_phase, n_ant=n_ant)


def pwc(target_phase, ref_phase, counts):
    """Paper's PWC: Phi - R phi_cal + 2 pi eps n, wrapped."""
    return np.angle(np.exp(1j * (target_phase - RATIO * ref_phase + TWO_PI * EPS * counts)))


def integer_closure(values, ant1, ant2, tri):
    """Sum of per-baseline integers around a triangle (no wrapping)."""
    total = 0
    for a, c in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
        b = np.flatnonzero((ant1 == min(a, c)) & (ant2 == max(a, c)))[0]
        total += values[b] if a < c else -values[b]
    return total


def circular_mean(x):
    x = x[np.isfinite(x)]
    return float(np.angle(np.mean(np.exp(1j * x))))


def test_solve_recovers_antenna_phases_relative_to_reference():
    s = scene(rho=20.0)
    ant_phase, ant_valid, ref_used, frame_break = solve_antenna_phases(
        s["ref_vis"], s["valid"], s["ant1"], s["ant2"], s["n_ant"], np.array([0], np.int64))
    assert np.all(ref_used == 0) and not frame_break.any()
    expected = s["trop"] - s["trop"][0]
    diff = np.angle(np.exp(1j * (ant_phase - expected)))[ant_valid]
    assert np.abs(diff).max() < 0.3 and np.sqrt(np.mean(diff ** 2)) < 0.05
    assert not ant_valid[3, :2000].any() and ant_valid[3, 2000:].all()


def test_closure_phases_antenna_mode_clean_baseline_mode_offset():
    """Late-starting antenna 3: baseline PWC starts its baselines at n0 = 0 and the closure
    phases carry 2 pi eps k; antenna-based PWC closes."""
    s = scene()
    ref_phase = np.angle(s["ref_vis"])
    triangles = np.array([t for t in itertools.combinations(range(4), 3)], np.int64)

    baseline = track_series(ref_phase, s["valid"], "naive")
    antenna = track_antennas(s["ref_vis"], s["valid"], s["ant1"], s["ant2"], 4, refants=[0],
                             antenna_tracker="smooth", half_window=3)
    offsets = {}
    for name, counts in (("baseline", baseline.counts), ("antenna", antenna.counts)):
        residual = pwc(s["target_phase"], ref_phase, counts)
        closure = closure_phases(residual, s["valid"], s["ant1"], s["ant2"], triangles)
        offsets[name] = np.array([circular_mean(c) for c in closure])
        # the closure offset is predicted by the count errors, which are constant per baseline
        err = np.array([slip_errors(counts[b], ref_phase[b], s["valid"][b], s["true_bl"][b])
                        for b in range(counts.shape[0])])
        k = np.array([np.median(e[v]) for e, v in zip(err, s["valid"])])
        k_closure = np.array([integer_closure(k, s["ant1"], s["ant2"], tri) for tri in triangles])
        predicted = np.angle(np.exp(1j * TWO_PI * EPS * k_closure))
        assert np.allclose(np.angle(np.exp(1j * (offsets[name] - predicted))), 0, atol=np.radians(3))
    # closure noise of the mean is ~1 deg; the smallest offset 2 pi eps k is 8.37 deg
    assert np.abs(offsets["antenna"]).max() < np.radians(3.0)
    # triangles with antenna 3 are offset by a multiple of 2 pi eps in baseline mode
    assert np.abs(offsets["baseline"]).max() > np.radians(5.0)
    assert np.abs(offsets["baseline"][0]) < np.radians(3.0)      # triangle (0,1,2): no late start


def test_reference_antenna_change_keeps_phases_continuous():
    s = scene(rho=10.0)
    valid = s["valid"].copy()
    # antenna 0 (first reference) drops out for 500 s
    valid[(s["ant1"] == 0) | (s["ant2"] == 0), 4000:4500] = False
    ant_phase, ant_valid, ref_used, frame_break = solve_antenna_phases(
        s["ref_vis"], valid, s["ant1"], s["ant2"], 4, np.array([0, 1], np.int64))
    assert np.all(ref_used[4000:4500] == 1) and np.all(ref_used[4500:] == 0)
    assert not frame_break.any()
    for p in (1, 2, 3):
        ok = ant_valid[p, 1:] & ant_valid[p, :-1]
        steps = np.angle(np.exp(1j * np.diff(ant_phase[p])))[ok]
        assert np.abs(steps).max() < 1.0
    result = track_antennas(s["ref_vis"], valid, s["ant1"], s["ant2"], 4, refants=[0, 1],
                            antenna_tracker="smooth", half_window=3)
    ref_phase = np.angle(s["ref_vis"])
    for b in range(6):
        err = slip_errors(result.counts[b], ref_phase[b], valid[b], s["true_bl"][b])
        assert count_slips(err, valid[b])[0] == 0


def test_antenna_mode_beats_baseline_tracking_at_low_snr():
    """At per-baseline SNR 2 each antenna solution combines 3 baselines: fewer slips."""
    s = scene(n_time=20000, starts=(0, 0, 0, 0), rho=2.0, seed=5)
    ref_phase = np.angle(s["ref_vis"])
    naive = track_series(ref_phase, s["valid"], "naive")
    antenna = track_antennas(s["ref_vis"], s["valid"], s["ant1"], s["ant2"], 4, refants=[0],
                             antenna_tracker="naive")
    total = {}
    for name, res in (("naive", naive), ("antenna", antenna)):
        total[name] = sum(count_slips(slip_errors(res.counts[b], ref_phase[b], s["valid"][b],
                                                  s["true_bl"][b]), s["valid"][b])[0] for b in range(6))
    assert total["naive"] > 100
    assert total["antenna"] < total["naive"] / 10


def test_complex64_and_flags():
    s = scene(n_time=3000, rho=8.0)
    valid = s["valid"].copy()
    valid[:, ::2] &= np.arange(6)[:, None] % 2 == 0        # alternating flags on odd baselines
    r128 = track_antennas(s["ref_vis"], valid, s["ant1"], s["ant2"], 4, refants=[0], half_window=2)
    r64 = track_antennas(s["ref_vis"].astype(np.complex64), valid, s["ant1"], s["ant2"], 4,
                         refants=[0], half_window=2)
    assert np.array_equal(r128.counts, r64.counts)
    # a fully flagged baseline gets zeros and no segments
    valid[2] = False
    res = track_antennas(s["ref_vis"], valid, s["ant1"], s["ant2"], 4, refants=[0])
    assert not res.counts[2].any() and np.all(res.segment[2] == -1)
    # one sample
    one = track_antennas(s["ref_vis"][:, 2500:2501], s["valid"][:, 2500:2501], s["ant1"], s["ant2"], 4)
    assert one.counts.shape == (6, 1)
    with pytest.raises(InputError, match="complex"):
        track_antennas(np.angle(s["ref_vis"]), valid, s["ant1"], s["ant2"], 4)


def test_antenna_mode_on_a_measurement_set(tmp_path):
    """Write the scene's 86 GHz visibilities to a real MS, read them back with casacore,
    lay them out, track per antenna and check closures of the PWC residual."""
    from casacore import tables as pt

    from hitops.io.layout import baseline_time_layout
    from hitops.io.ms_create import ArrayLayout, Band, Field, create_ms

    s = scene(n_time=2400, starts=(0, 0, 0, 800), seed=9)
    n_bl, n_time = s["ref_vis"].shape
    t0 = 5.1e9
    rows_b, rows_t = np.nonzero(s["valid"].T)[::-1]
    order = np.lexsort((rows_b, rows_t))
    rows_b, rows_t = rows_b[order], rows_t[order]
    vis = s["ref_vis"][rows_b, rows_t]
    positions = np.array([[2225039.5297, -5441197.6292, -2479303.3597],
                          [5088967.74544, -301681.18586, 3825012.20561],
                          [4524000.43, 468042.14, 4460309.76],
                          [-5464555.493, -2492927.989, 2150797.176]])
    layout = ArrayLayout(["AP", "PV", "PB", "SM"], ["APEX", "IRAM30", "NOEMA", "JCMT"],
                         positions, np.array([12.0, 30.0, 50.0, 15.0]))
    ms = create_ms(tmp_path / "ref86.ms", layout, Band(86e9, 2e9, ("RR",)),
                   Field("M87", 3.276, 0.2163),
                   {"TIME": t0 + rows_t.astype(float), "ANTENNA1": s["ant1"][rows_b],
                    "ANTENNA2": s["ant2"][rows_b], "UVW": np.zeros((rows_b.size, 3)),
                    "DATA": vis[:, None]})
    with pt.table(str(ms), ack=False) as tab:
        time = tab.getcol("TIME")
        a1 = tab.getcol("ANTENNA1")
        a2 = tab.getcol("ANTENNA2")
        data = tab.getcol("DATA")[:, 0, 0]
        flag = tab.getcol("FLAG")[:, 0, 0]
    assert data.dtype == np.complex64
    lay = baseline_time_layout(time, a1, a2)
    grid_index, dt = grid_positions(lay.times, strict=True)
    n_grid = int(grid_index[-1]) + 1
    assert n_grid == n_time and dt == pytest.approx(1.0)
    ref_vis = np.zeros((lay.n_bl, n_grid), np.complex64)
    valid = np.zeros((lay.n_bl, n_grid), bool)
    ref_vis[:, grid_index] = lay.to_grid(data, 0)
    valid[:, grid_index] = lay.to_grid(~flag, False)
    result = track_antennas(ref_vis, valid, lay.ant1, lay.ant2, 4, refants=[1, 2])
    # the layout's baselines are the scene's (same ordering of pairs)
    assert np.array_equal(lay.ant1, s["ant1"]) and np.array_equal(lay.ant2, s["ant2"])
    residual = pwc(s["target_phase"], np.angle(ref_vis.astype(np.complex128)), result.counts)
    triangles = np.array(list(itertools.combinations(range(4), 3)), np.int64)
    closure = closure_phases(residual, valid, lay.ant1, lay.ant2, triangles)
    # thermal noise only: the smallest possible offset 2 pi eps k is 8.37 deg
    assert max(abs(circular_mean(c)) for c in closure) < np.radians(3.0)
    summary = result.extra["antenna"].summary(names=layout.names)
    assert [row["name"] for row in summary] == ["AP", "PV", "PB", "SM"]
    assert all(row["jumps"] == 0 for row in summary)


def test_grid_positions_reject_irregular_times_when_strict():
    index, dt = grid_positions(np.array([0.0, 1.0, 2.0, 10.0, 11.0]), strict=True)
    assert index.tolist() == [0, 1, 2, 10, 11] and dt == 1.0
    with pytest.raises(InputError, match="regular"):
        grid_positions(np.array([0.0, 1.0, 2.5, 3.0]), strict=True)
    # calibrate's form: within scans only, and off-grid times fall back to the union index
    index, dt = grid_positions(np.array([0.0, 1.0, 2.0, 50.0, 51.0]), np.array([0, 0, 0, 1, 1]))
    assert index.tolist() == [0, 1, 2, 50, 51] and dt == 1.0
    index, dt = grid_positions(np.array([0.0, 1.0, 2.5, 3.0]))
    assert index.tolist() == [0, 1, 2, 3]
