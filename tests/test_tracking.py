"""Robust phase-wrap tracking (issue 6): theory, low SNR, gaps, jumps, extreme cases."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hitops.errors import InputError
from hitops.tracking.count import count_wraps
from hitops.testing.slips import count_slips, slip_errors
from hitops.tracking.smooth_kernel import track_wraps_smooth
from hitops.simulate.troposphere import fbm_circulant
from hitops.tracking import theory
from hitops.tracking.windows import half_windows
from track_grids import scan_grid  # tests/ is on sys.path (rootdir-relative)

TWO_PI = 2.0 * np.pi


def kolmogorov_track(n_time, coherence_s, seed):
    """Unwrapped Kolmogorov phase (rad) at 1 s sampling, from the simulator's exact generator."""
    rng = np.random.default_rng(seed)
    return fbm_circulant(n_time, 1, 5.0 / 6.0, rng)[0] * theory.kolmogorov_step_sigma(1.0, coherence_s)


def noisy_phase(true_phase, rho, seed):
    rng = np.random.default_rng(seed)
    noise = (rng.standard_normal(true_phase.size) + 1j * rng.standard_normal(true_phase.size)) / rho
    return np.angle(np.exp(1j * true_phase) + noise)


def slips(counts, phase, valid, truth):
    return count_slips(slip_errors(counts, phase, valid, truth), valid)


# ---------------------------------------------------------------- theory


@pytest.mark.parametrize("rho,expected", [(2, 3.42e-3), (3, 9.32e-5), (4, 1.22e-6), (5, 7.09e-9)])
def test_exact_itoh_failure_matches_guide(rho, expected):
    assert theory.itoh_failure_probability(rho) == pytest.approx(expected, rel=0.01)


def test_exact_failure_is_converged_and_gaussian_form_is_optimistic():
    coarse = theory.itoh_failure_probability(2.0, n_grid=20001)
    fine = theory.itoh_failure_probability(2.0, n_grid=160001)
    assert coarse == pytest.approx(fine, rel=1e-3)
    # the erfc form is more than 100x too small at rho = 2
    assert theory.gaussian_failure_probability(2.0) < coarse / 100
    # a true step makes failure more likely; pi is a coin toss at any SNR
    assert theory.itoh_failure_probability(3.0, step=1.0) > theory.itoh_failure_probability(3.0)
    assert theory.itoh_failure_probability(50.0, step=np.pi) == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("rho,n_steps", [(2.0, 2_000_000), (3.0, 4_000_000)])
def test_monte_carlo_failures_match_theory_and_naive_tracker(rho, n_steps):
    """Noise phases of a constant phasor: |theta_2 - theta_1| > pi as often as theory says,
    and the naive tracker's count error changes exactly at those steps."""
    truth = np.zeros(n_steps + 1)
    phase = noisy_phase(truth, rho, seed=int(rho * 10))
    failures = int(np.sum(np.abs(np.diff(phase)) > np.pi))
    expected = theory.itoh_failure_probability(rho) * n_steps
    assert abs(failures - expected) < 5 * np.sqrt(expected)
    valid = np.ones(phase.size, bool)
    err = slip_errors(count_wraps(phase, valid), phase, valid, truth)
    assert int(np.sum(np.abs(np.diff(err)))) == failures


def test_theory_inputs_are_checked():
    with pytest.raises(InputError, match="SNR"):
        theory.itoh_failure_probability(-1.0)
    with pytest.raises(InputError, match="ratio"):
        theory.slip_phase_step(0.0)


def test_recommended_windows_grow_as_snr_falls():
    halves = [theory.recommended_half_window(rho, coherence_time=33.0) for rho in (1.5, 2.0, 3.0, 5.0)]
    assert halves == sorted(halves, reverse=True)
    assert halves[-1] >= 1 and halves[0] <= 16
    assert 5 <= theory.recommended_max_gap(33.0) <= 33
    assert theory.gap_bridge_failure_probability(5.0, 33.0) < theory.gap_bridge_failure_probability(60.0, 33.0)


# ---------------------------------------------------------------- low SNR


@pytest.mark.parametrize("rho", [2.0, 3.0])
def test_robust_tracker_removes_slips_at_low_snr(rho):
    """A 12-h track at 1 s: naive Itoh slips ~ P * 43200 times, the smoothed tracker ~never."""
    truth = kolmogorov_track(43200, coherence_s=33.0, seed=7)
    phase = noisy_phase(truth, rho, seed=8)
    valid = np.ones(truth.size, bool)
    naive, _ = slips(count_wraps(phase, valid), phase, valid, truth)
    half = theory.recommended_half_window(rho, coherence_time=33.0)
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, half_window=half)
    robust, transients = slips(counts, phase, valid, truth)
    expected_naive = theory.itoh_failure_probability(rho) * truth.size
    if rho == 2.0:
        assert naive > 0.5 * expected_naive > 50
    assert robust == 0
    assert segment.max() == 0 and not bridged.any() and not np.any(jump)
    # the truth wraps many times, so the test exercises real wrap counting
    assert np.ptp(np.round(truth / TWO_PI)) >= 5


def test_smoothed_counts_agree_with_naive_at_high_snr():
    truth = kolmogorov_track(5000, coherence_s=10.0, seed=3)
    phase = noisy_phase(truth, 30.0, seed=4)
    valid = np.ones(truth.size, bool)
    naive = count_wraps(phase, valid)
    robust = track_wraps_smooth(phase, valid, half_window=3)[0]
    assert np.array_equal(naive - naive[0], robust - robust[0])


def test_smooth_tracker_counts_a_clean_ramp_like_count():
    phase = np.angle(np.exp(1j * np.linspace(0, 20, 200)))
    valid = np.ones(200, bool)
    assert np.array_equal(track_wraps_smooth(phase, valid)[0], count_wraps(phase, valid))


def test_inputs_are_not_mutated():
    phase = noisy_phase(kolmogorov_track(500, 20.0, 1), 3.0, 2)
    valid = np.ones(500, bool)
    valid[100:120] = False
    before = phase.copy(), valid.copy()
    track_wraps_smooth(phase, valid)
    assert np.array_equal(phase, before[0]) and np.array_equal(valid, before[1])


# ---------------------------------------------------------------- gaps


def test_gap_bridging_predicts_across_short_gaps():
    """A steady 0.5 rad/s drift: across a 10 s gap the phase moves 5 rad (> pi),
    which naive tracking miscounts and bridging gets right."""
    n_time = 400
    truth = 0.5 * np.arange(n_time) + 0.3
    phase = np.angle(np.exp(1j * truth))
    valid = np.ones(n_time, bool)
    valid[100:110] = False
    valid[250:275] = False
    naive, _ = slips(count_wraps(phase, valid), phase, valid, truth)
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, half_window=3, max_gap=30)
    robust, _ = slips(counts, phase, valid, truth)
    assert naive >= 1
    assert robust == 0
    assert np.flatnonzero(bridged).tolist() == [110, 275]
    assert set(segment[valid]) == {0} and np.all(segment[~valid] == -1)
    # invalid samples carry the previous count
    assert np.all(counts[100:110] == counts[99])


def test_bridging_on_turbulent_track_with_many_gaps():
    truth = kolmogorov_track(43200, coherence_s=33.0, seed=11)
    phase = noisy_phase(truth, 4.0, seed=12)
    rng = np.random.default_rng(13)
    valid = np.ones(truth.size, bool)
    starts = rng.choice(np.arange(100, 43000, 100), size=150, replace=False)
    lengths = rng.integers(1, 21, size=starts.size)
    for s, g in zip(starts, lengths):
        valid[s:s + g] = False
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, half_window=3, max_gap=30)
    assert slips(counts, phase, valid, truth)[0] == 0
    assert bridged.sum() == len(starts)
    assert segment.max() == 0


def test_long_gap_starts_a_reported_segment():
    truth = kolmogorov_track(3000, coherence_s=33.0, seed=5)
    phase = noisy_phase(truth, 5.0, seed=6)
    valid = np.ones(truth.size, bool)
    valid[1000:1200] = False          # 200 s > max_gap
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, max_gap=30)
    assert segment[999] == 0 and segment[1200] == 1 and segment.max() == 1
    assert not bridged[1200]
    err = slip_errors(counts, phase, valid, truth)
    # within each segment the count is exact; across the long gap it is only a best guess
    assert count_slips(err, valid & (segment == 0))[0] == 0
    assert count_slips(err, valid & (segment == 1))[0] == 0


# ---------------------------------------------------------------- jumps


def test_instrumental_jumps_are_detected_and_segmented():
    truth = kolmogorov_track(20000, coherence_s=33.0, seed=21)
    observed = truth.copy()
    observed[8000:] += 2.5            # instrumental jumps, not wraps
    observed[14000:] -= np.pi
    phase = noisy_phase(observed, 3.0, seed=22)
    valid = np.ones(truth.size, bool)
    window, thr = theory.recommended_jump_params(3.0, 33.0)
    assert thr > 0
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, half_window=3,
                                                                 jump_window=window, jump_threshold=thr)
    found = np.flatnonzero(jump)
    assert len(found) == 2
    assert abs(found[0] - 8000) <= 2 and abs(found[1] - 14000) <= 2
    assert jump[found[0]] == pytest.approx(2.5, abs=0.4)
    assert abs(abs(jump[found[1]]) - np.pi) < 0.4
    assert segment.max() == 2
    err = slip_errors(counts, phase, valid, observed)
    for s in range(3):
        assert count_slips(err, segment == s)[0] == 0      # no slip inside any segment
    # naive tracking takes the pi jump for a wrap about half the time; the
    # segment boundary is what makes the ambiguity visible instead of silent


@pytest.mark.parametrize("rho,coherence_s", [(2.0, 33.0), (3.0, 33.0), (30.0, 10.0)])
def test_no_false_jumps_on_turbulence(rho, coherence_s):
    """12 h of turbulence with the recommended jump parameters: no false jumps,
    while a 3 rad jump added to the same track is found."""
    truth = kolmogorov_track(43200, coherence_s=coherence_s, seed=31)
    valid = np.ones(truth.size, bool)
    window, thr = theory.recommended_jump_params(rho, coherence_s)
    phase = noisy_phase(truth, rho, seed=int(rho))
    _, segment, _, _, jump = track_wraps_smooth(phase, valid, half_window=5, jump_window=window,
                                                jump_threshold=thr)
    assert not np.any(jump) and segment.max() == 0
    observed = truth + 3.0 * (np.arange(truth.size) >= 30000)
    phase = noisy_phase(observed, rho, seed=int(rho))
    counts, segment, _, _, jump = track_wraps_smooth(phase, valid, half_window=5, jump_window=window,
                                                     jump_threshold=thr)
    assert np.flatnonzero(jump).tolist() in ([29999], [30000], [30001])
    err = slip_errors(counts, phase, valid, observed)
    assert count_slips(err, segment == 0)[0] == 0 and count_slips(err, segment == 1)[0] == 0


def test_jump_detection_is_switched_off_where_turbulence_hides_jumps():
    assert theory.recommended_jump_params(1.5, 10.0)[1] == 0.0
    assert theory.recommended_jump_params(3.0, 33.0)[1] > 0.0


# ---------------------------------------------------------------- extreme cases


def test_one_sample_series():
    for tracker in (count_wraps, lambda p, v: track_wraps_smooth(p, v)[0]):
        assert tracker(np.array([3.0]), np.array([True])).tolist() == [0]
    counts, segment, suspect, bridged, jump = track_wraps_smooth(np.array([-3.1]), np.array([True]))
    assert segment.tolist() == [0] and not suspect.any()


def test_fully_flagged_and_empty_series():
    phase = np.linspace(-3, 3, 50)
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, np.zeros(50, bool))
    assert not counts.any() and np.all(segment == -1) and not suspect.any()
    assert track_wraps_smooth(np.zeros(0), np.zeros(0, bool))[0].size == 0
    # NaN phases count as flagged
    counts, segment, *_ = track_wraps_smooth(np.full(10, np.nan), np.ones(10, bool))
    assert np.all(segment == -1) and not counts.any()


def test_alternating_flags():
    truth = 0.4 * np.arange(1000)                    # 0.8 rad between valid samples
    phase = np.angle(np.exp(1j * truth))
    valid = np.zeros(1000, bool)
    valid[::2] = True
    counts, segment, suspect, bridged, jump = track_wraps_smooth(phase, valid, half_window=4, max_gap=30)
    assert slips(counts, phase, valid, truth)[0] == 0
    assert bridged.sum() == 499 and segment.max() == 0
    assert np.array_equal(counts[1::2], counts[::2])  # flagged samples carry the previous count


def test_reference_phase_exactly_at_plus_minus_pi():
    """A phasor sitting at -1: its phase flips between +pi and -pi with no real motion."""
    phase = np.where(np.arange(100) % 3 == 0, -np.pi, np.pi)
    valid = np.ones(100, bool)
    for counts in (count_wraps(phase, valid), track_wraps_smooth(phase, valid)[0]):
        unwrapped = phase - TWO_PI * counts
        assert np.allclose(unwrapped, unwrapped[0])
    # a slow rotation through the boundary, with samples exactly on it
    truth = np.pi + np.linspace(-1, 1, 201) * 0.5
    phase = np.angle(np.exp(1j * truth))
    phase[100] = -np.pi
    counts = track_wraps_smooth(phase, valid[:1].repeat(201), half_window=2)[0]
    assert np.allclose(np.diff(phase - TWO_PI * counts), 0.005, atol=1e-9)


def test_complex64_input():
    """Phases taken from complex64 visibilities (float32 atan2 can exceed pi by 1e-7)."""
    truth = kolmogorov_track(20000, coherence_s=20.0, seed=41)
    rng = np.random.default_rng(42)
    vis = (np.exp(1j * truth) + (rng.standard_normal(truth.size) + 1j * rng.standard_normal(truth.size)) / 3.0)
    vis64 = vis.astype(np.complex64)
    valid = np.ones(truth.size, bool)
    phase32 = np.angle(vis64).astype(np.float64)
    phase128 = np.angle(vis64.astype(np.complex128))
    c32 = track_wraps_smooth(phase32, valid, half_window=3)[0]
    c128 = track_wraps_smooth(phase128, valid, half_window=3)[0]
    assert np.array_equal(c32, c128)
    assert slips(c128, phase128, valid, truth)[0] == 0
    edge = np.array([np.float32(np.pi), -np.float32(np.pi)] * 5, dtype=np.float64)  # 3.14159274 > pi
    assert np.allclose(edge - TWO_PI * track_wraps_smooth(edge, np.ones(10, bool))[0], edge[0])


def test_million_sample_track_is_fast():
    truth = kolmogorov_track(1_000_000, coherence_s=33.0, seed=51)
    phase = noisy_phase(truth, 3.0, seed=52)
    valid = np.ones(truth.size, bool)
    track_wraps_smooth(phase[:100], valid[:100])      # compile / load cache outside the timing
    t0 = time.perf_counter()
    counts, segment, *_ = track_wraps_smooth(phase, valid, half_window=3, jump_threshold=2.0)
    elapsed = time.perf_counter() - t0
    assert elapsed < 5.0
    assert slips(counts, phase, valid, truth)[0] <= 1
    assert counts.dtype == np.int64


@pytest.mark.parametrize("ratio", [3.0 - 1e-7, 3.0 + 1e-7, 3.0 - 1e-6, 3.0 + 1e-6])
def test_ratio_near_integer_from_either_side(ratio):
    """A wrap (or a slip) costs 2 pi eps at the target; near an integer R that is ~0 mod 2 pi."""
    step = theory.slip_phase_step(ratio)
    assert abs(step) <= TWO_PI * 1.01e-6
    # PWC with tracked counts then equals CFPT up to that tiny step per wrap
    truth = 0.3 * np.arange(300)
    phase = np.angle(np.exp(1j * truth))
    counts = track_wraps_smooth(phase, np.ones(300, bool))[0]
    target = np.angle(np.exp(1j * ratio * truth))
    eps = ratio - np.floor(ratio)
    pwc = np.angle(np.exp(1j * (target - ratio * phase + TWO_PI * eps * counts)))
    assert np.allclose(pwc, 0.0, atol=1e-6)


def test_ratio_below_one():
    """R < 1 (transfer from a higher to a lower frequency): r = 0, eps = R."""
    ratio = 86.0 / 230.0
    assert theory.slip_phase_step(ratio) == pytest.approx(TWO_PI * ratio - TWO_PI * round(ratio))
    truth = kolmogorov_track(20000, coherence_s=10.0, seed=61)
    phase = noisy_phase(truth, 2.5, seed=62)
    valid = np.ones(truth.size, bool)
    counts = track_wraps_smooth(phase, valid, half_window=3)[0]
    target = ratio * truth
    pwc = np.angle(np.exp(1j * (target - ratio * phase + TWO_PI * ratio * counts)))
    # residual is thermal only (R * noise phase): no persistent offsets
    assert abs(np.angle(np.mean(np.exp(1j * pwc[:10000])) / np.mean(np.exp(1j * pwc[10000:])))) < 0.05


# ---------------------------------------------------------------- station terms


def test_station_terms_round_trip():
    from hitops.tracking import stations

    tsys = stations.system_temperature(30.0, 0.1, 30.0, t_atm=260.0)
    # Tsys* = (T_rx + T_atm (1 - e^-tau X)) e^(tau X), X = 2 at 30 deg
    assert tsys == pytest.approx((30 + 260 * (1 - np.exp(-0.2))) * np.exp(0.2))
    sefd_pv = stations.sefd(tsys, 30.0)
    rho = stations.per_sample_snr(1.1, sefd_pv, sefd_pv, 2e9, 1.0)
    sigma = np.sqrt(sefd_pv * sefd_pv / (2 * 2e9 * 1.0)) / 0.88
    assert rho == pytest.approx(1.1 / sigma)
    limit = stations.max_sefd_product(3.0, 1.1, 2e9, 1.0)
    tau = stations.max_opacity(limit, 30.0, 30.0, 30.0)
    at_limit = stations.sefd(stations.system_temperature(30.0, tau, 30.0), 30.0)
    assert at_limit == pytest.approx(limit, rel=1e-6)
    assert np.isnan(stations.max_opacity(1.0, 30.0, 30.0, 30.0))
    # the naive threshold for one slip per 12 h sits between rho = 3 and 4
    rho_1 = stations.rho_for_slip_rate(1.0)
    assert 3.0 < rho_1 < 4.0
    assert theory.itoh_failure_probability(rho_1) * 43199 == pytest.approx(1.0, rel=0.02)
    with pytest.raises(InputError, match="elevation"):
        stations.system_temperature(30.0, 0.1, 0.0)


def test_dask_wrapper_matches_numpy():
    import dask.array as da

    from hitops.tracking.modes import track_series, track_series_dask

    truth = np.stack([kolmogorov_track(3000, 20.0, seed) for seed in range(5)])
    phase = np.stack([noisy_phase(t, 2.5, i) for i, t in enumerate(truth)])
    valid = np.ones(phase.shape, bool)
    valid[:, 1000:1010] = False
    expected = track_series(phase, valid, "smooth", half_window=4)
    lazy = track_series_dask(da.from_array(phase, chunks=(2, -1)), da.from_array(valid, chunks=(2, -1)),
                             "smooth", half_window=4)
    assert np.array_equal(lazy["counts"].compute(), expected.counts)
    assert np.array_equal(lazy["bridged"].compute(), expected.bridged)
    with pytest.raises(InputError, match="time axis"):
        track_series_dask(da.from_array(phase, chunks=(2, 100)), da.from_array(valid, chunks=(2, 100)))


def test_count_slips_separates_outliers_from_slips():
    valid = np.ones(12, bool)
    outliers = np.array([0, 0, 1, 0, 0, -1, -1, 0, 1, 0, 0, 0])
    assert count_slips(outliers, valid) == (0, 4)
    slip = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1])
    assert count_slips(slip, valid) == (1, 0)
    long_excursion = np.array([0, 0, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0])
    assert count_slips(long_excursion, valid) == (2, 0)
    assert count_slips(long_excursion, valid, max_transient=4) == (0, 4)


def test_zero_window_is_naive_and_zero_max_gap_segments_every_gap():
    truth = kolmogorov_track(3000, 20.0, seed=71)
    phase = noisy_phase(truth, 20.0, seed=72)
    valid = np.ones(truth.size, bool)
    counts = track_wraps_smooth(phase, valid, half_window=0)[0]
    assert np.array_equal(counts, count_wraps(phase, valid))
    valid[[500, 1500, 2500]] = False
    _, segment, _, bridged, _ = track_wraps_smooth(phase, valid, max_gap=0)
    assert segment.max() == 3 and not bridged.any()


def test_half_windows_are_the_theory_evaluated_sample_by_sample():
    """Each sample's half-window is the theory's for its own rounded (SNR, t_c), however the
    samples are grouped: pairs that share an SNR but not a t_c, or a t_c but not an SNR,
    get their own windows (a lookup keyed on one of the two would not), and the samples
    with no signal, or unknown inputs, follow their own rules."""
    rng = np.random.default_rng(7)
    grid_rho, grid_tc = np.meshgrid([0.8, 1.6, 3.0, 9.0], [3.0, 8.0, 30.0, 120.0])
    pick = rng.integers(0, grid_rho.size, 5000)
    # a spread well below the rounding to 2 digits: many samples share each rounded pair
    rho = grid_rho.ravel()[pick] * (1 + rng.uniform(-1e-3, 1e-3, pick.size))
    t_c = grid_tc.ravel()[pick] * (1 + rng.uniform(-1e-3, 1e-3, pick.size))
    rho[:3], t_c[3:5] = [0.0, np.nan, -1.0], [np.nan, 0.0]
    windows = half_windows(rho, t_c, dt=1.0)
    expected = np.ones(rho.size, np.int64)
    for i, (r, t) in enumerate(zip(rho, t_c)):
        if np.isfinite(r) and r > 0 and np.isfinite(t) and t > 0:
            expected[i] = theory.recommended_half_window(float(_two_digits(r)),
                                                         float(_two_digits(max(t, 1.0))), 1.0)
        elif np.isfinite(r) and r <= 0 and np.isfinite(t):
            expected[i] = min(max(int((t - 1) // 2), 1), 200)
    assert np.array_equal(windows, expected)
    # the grid's pairs give at least a few distinct windows, so the check is not vacuous
    assert np.unique(windows[5:]).size >= 4


def _two_digits(x: float) -> float:
    """x rounded to 2 significant digits, written out here (not hitops's two_digits)."""
    digits = np.floor(np.log10(x)) - 1
    return np.round(x / 10.0 ** digits) * 10.0 ** digits


def test_per_sample_windows_follow_local_coherence():
    """Turbulence 10x faster in the second half (low elevation): a long fixed window slips
    there, per-sample windows from the local coherence time do not."""
    slow = kolmogorov_track(20000, coherence_s=60.0, seed=81)
    fast = kolmogorov_track(20000, coherence_s=4.0, seed=82)
    truth = np.concatenate([slow, slow[-1] + fast])
    phase = noisy_phase(truth, 3.0, seed=83)
    valid = np.ones(truth.size, bool)
    t_c = np.where(np.arange(truth.size) < 20000, 60.0, 4.0)
    windows = half_windows(3.0, t_c)
    assert windows[0] > windows[-1] >= 1
    fixed = track_wraps_smooth(phase, valid, half_window=int(windows[0]))[0]
    local = track_wraps_smooth(phase, valid, half_window=int(windows[0]), half_windows=windows)[0]
    assert slips(fixed, phase, valid, truth)[0] > 0
    assert slips(local, phase, valid, truth)[0] <= 2
    sin_el = np.array([1.0, 0.5, np.sin(np.radians(10))])
    assert np.allclose(theory.local_coherence_time(33.0, sin_el), 33.0 * sin_el ** 0.6)


# ---------------------------------------------------------------- the count tracker (issue 12)

def test_split_at_gaps_gives_a_new_axis_with_a_scan_started_at_each_long_gap():
    """Gaps inside a SCAN_NUMBER longer than the limit start tracking scans (the number
    repeats); a gap at a scan change or a short one does not; the input axis is unchanged."""
    from hitops.tracking.grid import ScanAxis, ScanSplit

    times = np.array([0.0, 10, 20, 200, 210, 220, 400, 410, 430, 440])
    scan_of_time = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 1])
    axis = ScanAxis(np.array([3, 5]), scan_of_time)
    split, splits = axis.split_at_gaps(times, 50.0)
    assert splits == [ScanSplit(3, 200.0, 180.0)]
    assert np.array_equal(split.scan_numbers, [3, 3, 5]) and split.n_scan == 3
    assert np.array_equal(split.scan_of_time, [0, 0, 0, 1, 1, 1, 2, 2, 2, 2])
    assert np.array_equal(axis.scan_of_time, scan_of_time) and axis.n_scan == 2
    same, none = axis.split_at_gaps(times, 500.0)
    assert same is axis and none == []


def _count_reference(phase, valid, scan_of_time, carry):
    """transfer.track(count_wraps, ...) as it was before issue 12, written out as the oracle:
    count_wraps per scan run, the first run continuing the carried sample of the same scan."""
    from hitops.tracking.base import scan_runs
    from hitops.tracking.count import Carry

    n_bl, n_corr, _ = phase.shape
    wraps = np.zeros(phase.shape, np.int64)
    runs = scan_runs(scan_of_time)
    new = Carry(carry.last_phase.copy(), carry.has_last.copy(), carry.count.copy(),
                runs[-1][2] if runs else carry.last_scan)
    for b in range(n_bl):
        for c in range(n_corr):
            for i, (start, stop, scan) in enumerate(runs):
                ph, va = phase[b, c, start:stop], valid[b, c, start:stop]
                if i == 0 and scan == carry.last_scan and carry.has_last[b, c]:
                    n = count_wraps(np.concatenate(([carry.last_phase[b, c]], ph)),
                                    np.concatenate(([True], va)))[1:] + carry.count[b, c]
                else:
                    n = count_wraps(ph, va)
                wraps[b, c, start:stop] = n
            start, stop, scan = runs[-1]
            last = np.flatnonzero(valid[b, c, start:stop])
            if last.size:
                new.last_phase[b, c] = phase[b, c, start + last[-1]]
                new.has_last[b, c] = True
                new.count[b, c] = wraps[b, c, start + last[-1]]
            elif not (len(runs) == 1 and scan == carry.last_scan):
                new.has_last[b, c] = False
                new.count[b, c] = 0
    return wraps, new


def _count_case(seed=11, n_bl=3, n_corr=2, n_time=400):
    """Fast wrapping phases with scans, flagged runs and NaN samples."""
    rng = np.random.default_rng(seed)
    true = np.cumsum(rng.normal(0.0, 1.2, (n_bl, n_corr, n_time)), axis=-1)
    vis = np.exp(1j * true)
    valid = rng.random((n_bl, n_corr, n_time)) > 0.1
    valid[0, 0, 150:260] = False             # flagged across a scan change and chunk edges
    valid[1, :, 90:100] = False
    vis[2, 1, rng.integers(0, n_time, 30)] = np.nan + 0j
    scan = np.repeat([0, 0, 1, 1, 1, 3, 3, 4], n_time // 8)
    return vis, valid, scan


@pytest.mark.parametrize("chunk", [1, 7, 64, 97, 400])
def test_count_tracker_equals_the_transfer_counter_whole_and_chunked(chunk):
    from hitops.tracking.count import Carry, CountTracker

    vis, valid, scan = _count_case()
    n_bl, n_corr, n_time = vis.shape
    # NaN samples marked valid: count_wraps skips them, so the whole-track counts are the
    # transfer counter's, and chunked ones equal them (the carry skips them too)
    expected, _ = _count_reference(np.angle(vis), valid, scan, Carry.empty(n_bl, n_corr))
    tracker = CountTracker(scan_grid(scan, n_bl), ["RR", "LL"])
    assert tracker.context == 0 and tracker.extended(10, 20) == (10, 20)
    got = []
    for t0 in range(0, n_time, chunk):
        t1 = min(t0 + chunk, n_time)
        out = tracker.track(t0, t0, t1, t1, vis[..., t0:t1], valid[..., t0:t1], None)
        assert out.ref_exclude is None and out.segment_keys is None and out.ref_model is None
        got.append(out.ref_wraps)
    assert np.array_equal(np.concatenate(got, axis=-1), expected)
    # the reference counts restart in every scan, and the events do not count the restarts
    whole = CountTracker(scan_grid(scan, n_bl), ["RR", "LL"])
    whole.track(0, 0, n_time, n_time, vis, valid, None)
    assert np.array_equal(tracker.stats.per_series["wrap_events"],
                          whole.stats.per_series["wrap_events"])
    assert tracker.report(np.arange(n_time))["baselines"][0]["wrap_events"] > 0


def test_count_scans_continues_the_carry_like_the_transfer_counter():
    """Chunk by chunk with the carry, against the oracle; phases (float) pass through as they are."""
    from hitops.tracking.count import Carry, count_scans

    vis, valid, scan = _count_case(seed=12)
    valid &= np.isfinite(vis)            # as calibrate gathers them: unusable = invalid
    phase = np.where(valid, np.angle(vis), np.nan)
    carry_a = carry_b = Carry.empty(*vis.shape[:2])
    for t0, t1 in [(0, 33), (33, 150), (150, 151), (151, 400)]:
        a, carry_a = count_scans(phase[..., t0:t1], valid[..., t0:t1], scan[t0:t1], carry_a)
        b, carry_b = _count_reference(phase[..., t0:t1], valid[..., t0:t1], scan[t0:t1], carry_b)
        assert np.array_equal(a, b)
        assert np.array_equal(carry_a.count, carry_b.count)
        assert np.array_equal(carry_a.has_last, carry_b.has_last)
        assert carry_a.last_scan == carry_b.last_scan
    try:   # the transfer tasks' own counter, while it exists (issue 12 replaces it)
        from hitops.calibrate.transfer import track
    except ImportError:
        return
    carry = Carry.empty(*vis.shape[:2])
    old, _ = track(count_wraps, phase, valid, scan, carry)
    new, _ = count_scans(phase, valid, scan, carry)
    assert np.array_equal(old, new)
