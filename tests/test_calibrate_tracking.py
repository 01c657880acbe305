"""hitops calibrate with the robust trackers (issue 6 part B): --tracker smooth|antenna.

Each test takes a copy of a small Measurement Set pair with a known troposphere
(hitops.testing.make_pair; the ``new_pair`` fixture), corrupts the reference band (noise,
gaps, a late station, an instrumental jump) and checks that calibrate's
wrap counts, confidence numbers and flags come back as the truth says.

How a count error is read off the output: with a noiseless target band,
arg(PWC) = source - R theta + 2 pi eps e (mod 2 pi), theta the reference
noise phase and e = n_tracked - n_true.  Both source and theta are known, so
e is recovered modulo 43 (eps = 29/43), which is plenty for steps of +-1.

The antenna tracker transfers each baseline's antenna model R (A_p - A_q)
instead of the baseline's own reference phase, so its output keeps the target's
closure phases and carries R times the reference band's non-closing part
(``truth.ref_offset``) and the antenna model's noise; its count
errors are read off the output with that part removed (:func:`antenna_residual`)
and its slips as persistent steps of the smoothed residual
(:func:`antenna_slips`).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Signal, Troposphere, add_column, wrap
from hitops.errors import InputError, StationError
from hitops.tracking.antenna_kernel import closure_phases
from hitops.testing.slips import count_slips
from ms_columns import col, put  # tests/ is on sys.path (rootdir-relative)

EPS = 230.0 / 86.0 - 2


def flag_first_baseline(truth, *time_ranges):
    """Flag reference samples of baseline 0-1 in [start, stop) seconds from the first time.

    Returns (t_idx, first_bl): each target row's time index and whether it is on 0-1.
    """
    flag = col(truth.ref_ms, "FLAG")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    first_bl = (truth.ant1 == 0) & (truth.ant2 == 1)
    for start, stop in time_ranges:
        flag[first_bl & (t_idx >= start) & (t_idx < stop)] = True
    put(truth.ref_ms, "FLAG", flag)
    return t_idx, first_bl


def count_error(truth, out):
    """e = n_tracked - n_true per target row and correlation (see the module doc)."""
    ref_vis = col(truth.ref_ms, "DATA")[:, 0, :]      # same row order as the target here
    theta = wrap(np.angle(ref_vis) - truth.ref_phase_true)
    y = wrap(np.angle(out[:, 0, :]) - truth.source_phase + truth.ratio * theta)
    k = np.arange(43)
    grid = wrap(2 * np.pi * EPS * k)
    e = k[np.argmin(np.abs(wrap(y[..., None] - grid)), axis=-1)]
    return np.where(e > 21, e - 43, e)


def antenna_residual(truth, out):
    """arg(out) - (source + R ref_offset): 2 pi eps (k_p - k_q) plus the model's noise."""
    ideal = truth.source_phase + truth.ratio * truth.ref_offset
    return wrap(np.angle(out[:, 0, :]) - ideal)


def antenna_count_error(truth, out):
    """Noiseless antenna mode: the integer e of antenna_residual = 2 pi eps e (mod 2 pi)."""
    y = antenna_residual(truth, out)
    k = np.arange(43)
    e = k[np.argmin(np.abs(wrap(y[..., None] - wrap(2 * np.pi * EPS * k))), axis=-1)]
    return np.where(e > 21, e - 43, e)


def antenna_slips(truth, out, window=101, threshold_deg=58.0):
    """Persistent steps of the antenna-mode residual, over every baseline and correlation.

    The residual is averaged as a phasor over ``window`` samples; a count slip moves it
    by 2 pi eps (117 deg) for good, noise by a few degrees.  A run of consecutive
    samples whose means ``window`` apart differ by more than ``threshold_deg`` is one step.
    """
    y = np.exp(1j * antenna_residual(truth, out))
    total = 0
    kernel = np.ones(window) / window
    for a1, a2 in set(zip(truth.ant1.tolist(), truth.ant2.tolist())):
        sel = np.flatnonzero((truth.ant1 == a1) & (truth.ant2 == a2))
        sel = sel[np.argsort(truth.time[sel])]
        for c in range(y.shape[1]):
            mean = np.convolve(y[sel, c], kernel, mode="valid")
            big = np.abs(np.angle(mean[window:] * np.conj(mean[:-window]))) > np.radians(threshold_deg)
            total += int(np.sum(np.diff(np.concatenate([[0], big.astype(int)])) == 1))
    return total


def slips(truth, out, valid=None):
    """Persistent count changes summed over every baseline and correlation."""
    e = count_error(truth, out)
    total = 0
    for a1, a2 in set(zip(truth.ant1.tolist(), truth.ant2.tolist())):
        sel = np.flatnonzero((truth.ant1 == a1) & (truth.ant2 == a2))
        sel = sel[np.argsort(truth.time[sel])]
        for c in range(e.shape[1]):
            ok = np.ones(sel.size, bool) if valid is None else valid[sel, c]
            series = e[sel, c]
            if ok.sum() > 1:
                total += count_slips(np.ascontiguousarray(series), ok, 3)[0]
    return total


#: rho = 1.1 / 0.55 = 2 per sample: naive tracking fails ~1 step in 300
NOISY = PairSpec(n_ant=4, n_time=1500, seed=3,
                 troposphere=Troposphere(step_rad=0.1, drift_rad=0.03),
                 signal=Signal(sigma_ref=0.55))


def run(truth, column="OUT", **kw):
    rep = calibrate_flat(truth.ref_ms, truth.target_ms, output_column=column, overwrite=True, **kw)
    return col(truth.target_ms, column), rep


def test_smooth_removes_the_slips_of_naive_counting_at_snr_2(new_pair):
    truth = new_pair(NOISY)
    naive, _ = run(truth, tracker="count")
    smooth, rep = run(truth, tracker="smooth")
    antenna, rep_ant = run(truth, tracker="antenna")
    n_naive, n_smooth, n_ant = slips(truth, naive), slips(truth, smooth), antenna_slips(truth, antenna)
    # expected ~6 baselines x 2 corr x 1500 steps x 3.4e-3 x 0.7 persistent = 43
    assert 15 <= n_naive <= 90
    assert n_smooth == 0 and n_ant == 0
    # the antenna-mode measure sees the naive tracker's slips too (it is not blind)
    assert antenna_slips(truth, naive) >= 10
    assert rep["tracking"]["setup"]["snr_source"] == "data"
    assert rep["tracking"]["setup"]["half_window"] == "per-sample"
    assert rep_ant["tracking"]["setup"]["tracker"] == "antenna"
    assert {a["antenna"] for a in rep_ant["tracking"]["antennas"]} == {"AP", "SM", "PV", "GL"}


def test_per_sample_windows_from_sigma(new_pair):
    truth = new_pair(replace(NOISY, n_time=800))
    sigma = np.full(col(truth.ref_ms, "SIGMA").shape, 0.55, np.float32)
    put(truth.ref_ms, "SIGMA", sigma)
    out, rep = run(truth, tracker="smooth")
    assert rep["tracking"]["setup"]["snr_source"] == "sigma"
    assert slips(truth, out) == 0
    put(truth.ref_ms, "SIGMA", np.ones_like(sigma))          # CASA's uninformative default
    put(truth.ref_ms, "WEIGHT", np.full(sigma.shape, 1 / 0.55 ** 2, np.float32))
    _, rep = run(truth, tracker="smooth")
    assert rep["tracking"]["setup"]["snr_source"] == "weight"
    _, rep = run(truth, tracker="smooth", snr=2.0)
    assert rep["tracking"]["setup"]["snr_source"] == "fixed"
    assert rep["tracking"]["setup"]["half_window"] >= 3


@pytest.mark.parametrize("tracker", ["smooth", "antenna"])
def test_chunked_and_unchunked_outputs_agree(new_pair, tracker):
    truth = new_pair(replace(NOISY, n_time=900, n_scans=2))
    # a bridged gap, then a long gap that starts a new segment
    flag_first_baseline(truth, (100, 110), (200, 300))
    whole, rep_whole = run(truth, tracker=tracker)
    chunked, rep_chunked = run(truth, tracker=tracker, chunk_rows=500)
    assert rep_chunked["chunks"] > 5 and rep_whole["chunks"] == 1
    ok = col(truth.target_ms, "FLAG")[:, 0, :] == 0
    assert np.array_equal(np.abs(whole) > 0, np.abs(chunked) > 0)
    diff = np.angle(whole[:, 0, :] * np.conj(chunked[:, 0, :]))[ok]
    assert np.max(np.abs(diff)) < 1e-5
    strip = ("time_s", "timings_s", "chunks", "report_path")
    a = {k: v for k, v in rep_whole["tracking"].items() if k not in strip}
    b = {k: v for k, v in rep_chunked["tracking"].items() if k not in strip}
    assert a == b


def test_gaps_are_bridged_or_start_reported_segments(new_pair, caplog):
    # a reference band without non-closing phases: with 3 stations the antenna solve fits
    # them differently while one baseline is missing, which is not what is tested here
    truth = new_pair(PairSpec(n_ant=3, n_time=600, corr_types=("RR",), seed=5,
                              troposphere=Troposphere(step_rad=0.1, ref_offset_scale=0.0)))
    # 8 samples (< max_gap), then 100 samples (> max_gap)
    t_idx, first_bl = flag_first_baseline(truth, (100, 108), (300, 400))
    with caplog.at_level("INFO", logger="hitops"):
        out, rep = run(truth, tracker="smooth", coherence_time=30.0)
    entry = {e["baseline"]: e for e in rep["tracking"]["baselines"]}["AP-SM"]
    assert entry["bridged_gaps"] == 1
    assert entry["long_gap_segments"] == 1 and entry["segments"] == 2
    assert "best guess" in caplog.text and "AP-SM (1 gaps" in caplog.text
    assert "tracking AP-SM: 0 suspected slips" in caplog.text
    valid = col(truth.target_ms, "FLAG")[:, 0, :] == 0
    e = count_error(truth, out)
    sel = first_bl & valid[:, 0] & (t_idx < 300)
    assert np.unique(e[sel, 0]).size == 1          # bridged: no slip across the short gap
    # the report and the antenna mode: the long gap is resolved through the other baselines
    out_ant, rep_ant = run(truth, tracker="antenna", coherence_time=30.0)
    e_ant = antenna_count_error(truth, out_ant)
    for bl in [(0, 1), (0, 2), (1, 2)]:
        sel = (truth.ant1 == bl[0]) & (truth.ant2 == bl[1]) & valid[:, 0]
        assert np.unique(e_ant[sel, 0]).size == 1


def _late_station_pair(new_pair):
    truth = new_pair(PairSpec(n_ant=4, n_time=700, seed=11, corr_types=("RR", "LL"),
                              troposphere=Troposphere(step_rad=0.12, drift_rad=0.06,
                                                      phase_offset_rad=1.0)))
    flag = col(truth.ref_ms, "FLAG")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    late = ((truth.ant1 == 3) | (truth.ant2 == 3)) & (t_idx < 250)
    flag[late] = True                      # GL joins after 250 s at the reference band
    put(truth.ref_ms, "FLAG", flag)
    return truth


def _closures(truth, out, flag):
    """Closure phases (rad) of out - source over the triangles with station 3, per sample."""
    triangles = np.array([[0, 1, 3], [0, 2, 3], [1, 2, 3]], np.int64)
    n_time = np.unique(truth.time).size
    bls = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    phase = np.zeros((len(bls), n_time))
    valid = np.zeros((len(bls), n_time), bool)
    resid = wrap(np.angle(out[:, 0, 0]) - truth.source_phase[:, 0])
    for b, (p, q) in enumerate(bls):
        sel = np.flatnonzero((truth.ant1 == p) & (truth.ant2 == q))
        sel = sel[np.argsort(truth.time[sel])]
        phase[b] = resid[sel]
        valid[b] = ~flag[sel, 0, 0]
    a1 = np.array([p for p, _ in bls], np.int64)
    a2 = np.array([q for _, q in bls], np.int64)
    return closure_phases(phase, valid, a1, a2, triangles)


def test_antenna_mode_closes_where_baseline_mode_carries_2pi_eps_k(new_pair):
    """A station joining late: baseline PWC starts its baselines at n0 = 0, antenna PWC does not."""
    truth = _late_station_pair(new_pair)
    base, _ = run(truth, column="PWC_BL", tracker="count")
    flag = col(truth.target_ms, "FLAG")
    ant, rep = run(truth, column="PWC_ANT", tracker="antenna", refant="PV")
    assert np.array_equal(col(truth.target_ms, "FLAG"), flag)
    closure_bl = _closures(truth, base, flag)
    closure_ant = _closures(truth, ant, flag)
    ok = np.isfinite(closure_ant)
    assert ok.sum() > 3 * 400
    # baseline mode: constant closure errors on the 8.37 deg grid of 2 pi eps k, k != 0
    errs = np.degrees(np.abs(closure_bl[ok]))
    assert errs.max() > 8.0
    grid = np.degrees(wrap(2 * np.pi * EPS * np.arange(-10, 11)))
    assert np.all(np.min(np.abs(wrap(np.radians(errs[:, None] - np.abs(grid)[None]))), axis=1) < 1e-3)
    # antenna mode: the closure phases of the output are the target band's own, whatever
    # the reference band's baselines carry (noiseless: exact to float precision)
    closure_target = _closures(truth, col(truth.target_ms, "DATA"), flag)
    assert np.max(np.abs(wrap(closure_ant[ok] - closure_target[ok]))) < 1e-6
    assert rep["tracking"]["setup"]["refants"] == [2]


def test_antenna_mode_through_the_command_line(new_pair):
    import subprocess
    import sys
    from pathlib import Path

    truth = _late_station_pair(new_pair)
    hitops = Path(sys.executable).with_name("hitops")
    proc = subprocess.run([str(hitops), "calibrate", str(truth.ref_ms), str(truth.target_ms),
                           "--tracker", "antenna", "--refant", "PV,PB", "--coherence-time", "25",
                           "--solve-half-window", "0"], capture_output=True, text=True)
    # PB is not a station of this set
    assert proc.returncode == 2 and "PB" in proc.stderr and "ANTENNA" in proc.stderr
    proc = subprocess.run([str(hitops), "calibrate", str(truth.ref_ms), str(truth.target_ms),
                           "--tracker", "antenna", "--refant", "PV", "--coherence-time", "25",
                           "--solve-half-window", "0"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "tracking antenna GL:" in proc.stderr
    report = json.loads(Path(str(truth.target_ms) + ".hitops-calibrate.json").read_text())
    assert report["tracking"]["setup"]["solve_half_window"] == 0
    flag = col(truth.target_ms, "FLAG")
    closure = _closures(truth, col(truth.target_ms, "PWC_DATA"), flag)
    closure_target = _closures(truth, col(truth.target_ms, "DATA"), flag)
    ok = np.isfinite(closure)
    assert ok.sum() > 1000
    assert np.max(np.abs(wrap(closure[ok] - closure_target[ok]))) < 1e-6


def _jump_pair(new_pair):
    # slow drifts: the jump statistic compares window means jump_window samples apart,
    # so it measures the jump plus the phase trend over that distance
    truth = new_pair(PairSpec(n_ant=3, n_time=600, corr_types=("RR",), seed=7,
                              troposphere=Troposphere(step_rad=0.05, drift_rad=0.005),
                              signal=Signal(sigma_ref=0.1)))
    data = col(truth.ref_ms, "DATA")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    # an instrumental 2.5 rad jump of station PV (index 2) at the reference band only
    jump = np.where(t_idx >= 350, 2.5, 0.0)
    sign = np.where(truth.ant1 == 2, 1.0, np.where(truth.ant2 == 2, -1.0, 0.0))
    put(truth.ref_ms, "DATA", (data * np.exp(1j * sign * jump)[:, None, None]).astype(np.complex64))
    return truth, t_idx, sign != 0


@pytest.mark.parametrize("tracker", ["smooth", "antenna"])
def test_jumps_are_reported_with_times_and_flagged_on_request(new_pair, tracker):
    truth, t_idx, with_pv = _jump_pair(new_pair)
    flag_before = col(truth.target_ms, "FLAG").copy()
    _, rep = run(truth, tracker=tracker, jump_threshold=90.0, jump_window=5, coherence_time=60.0)
    rows = rep["tracking"]["antennas"] if tracker == "antenna" else rep["tracking"]["baselines"]
    found = [j for e in rows for j in e["jump_list"]]
    if tracker == "antenna":
        # the jump lands on PV, or on the other two if the solve is referred to PV
        assert found and all(abs(j["time_from_start_s"] - 350) <= 2 for j in found)
        assert any(e["antenna"] == "PV" and e["jumps"] == 1 for e in rows) or len(found) == 2
    else:
        by_bl = {e["baseline"]: e for e in rows}
        assert by_bl["AP-SM"]["jumps"] == 0
        for name in ("AP-PV", "SM-PV"):
            assert by_bl[name]["jumps"] == 1 and by_bl[name]["segments"] == 2
            (j,) = by_bl[name]["jump_list"]
            assert abs(j["time_from_start_s"] - 350) <= 2
            assert abs(abs(j["size_deg"]) - math.degrees(2.5)) < 15
    assert rep["samples"]["jump_flagged"] == 0
    assert np.array_equal(col(truth.target_ms, "FLAG"), flag_before)
    # --jump-action flag: the output after the jump is flagged (and reported)
    _, rep = run(truth, tracker=tracker, jump_threshold=90.0, jump_window=5, coherence_time=60.0,
                 jump_action="flag")
    flag = col(truth.target_ms, "FLAG")[:, 0, 0]
    assert rep["samples"]["jump_flagged"] >= 2 * 240
    assert np.all(flag[with_pv & (t_idx >= 352)])
    assert not flag[~with_pv].any() and not flag[t_idx < 340].any()
    # the same in ~60-time chunks (the jump falls inside one, its flags span several)
    _, rep_chunked = run(truth, tracker=tracker, jump_threshold=90.0, jump_window=5,
                         coherence_time=60.0, jump_action="flag", chunk_rows=200)
    assert rep_chunked["chunks"] >= 8
    assert np.array_equal(col(truth.target_ms, "FLAG")[:, 0, 0], flag)
    assert rep_chunked["samples"]["jump_flagged"] == rep["samples"]["jump_flagged"]


def test_count_tracker_is_the_default_and_warns_about_robust_options(new_pair, caplog):
    truth = new_pair(PairSpec(n_time=60, corr_types=("RR",)))
    with caplog.at_level("WARNING", logger="hitops"):
        _, rep = run(truth, half_window=4)
    assert rep["tracker"] == "count" and "--tracker count ignores --half-window" in caplog.text
    assert rep["tracking"]["setup"] == {"tracker": "count"}
    assert len(rep["tracking"]["baselines"]) == 6


@pytest.mark.parametrize("kwargs, match", [
    ({"tracker": "kalman"}, "--tracker"),
    ({"tracker": "smooth", "half_window": -2}, "--half-window"),
    ({"tracker": "smooth", "coherence_time": 0}, "--coherence-time"),
    ({"tracker": "smooth", "snr": -1}, "--snr"),
    ({"tracker": "smooth", "max_gap": -5}, "--max-gap"),
    ({"tracker": "smooth", "jump_threshold": 200}, "--jump-threshold"),
    ({"tracker": "smooth", "jump_window": 1.5}, "--jump-window"),
    ({"tracker": "smooth", "jump_action": "ignore"}, "--jump-action"),
    ({"tracker": "antenna", "solve_half_window": -3}, "--solve-half-window"),
    ({"tracker": "antenna", "refant": "XX"}, "--refant"),
])
def test_bad_tracking_options_leave_the_ms_unchanged(new_pair, kwargs, match):
    truth = new_pair(PairSpec(n_time=40, corr_types=("RR",)))
    with pt.table(str(truth.target_ms), ack=False) as t:
        before = (sorted(t.colnames()), t.getcol("FLAG").copy())
    error = StationError if "refant" in kwargs else InputError
    with pytest.raises(error, match=match):
        calibrate_flat(truth.ref_ms, truth.target_ms, **kwargs)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert sorted(t.colnames()) == before[0]
        assert np.array_equal(t.getcol("FLAG"), before[1])
    assert not (truth.target_ms.parent / (truth.target_ms.name + ".hitops-calibrate.json")).exists()


def test_extreme_cases_one_sample_fully_flagged_and_cross_hands(new_pair):
    truth = new_pair(PairSpec(n_ant=3, n_time=50, corr_types=("RR", "RL", "LR", "LL"), seed=2))
    flag = col(truth.ref_ms, "FLAG")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    flag[(truth.ant1 == 0) & (truth.ant2 == 1)] = True                          # fully flagged
    flag[(truth.ant1 == 0) & (truth.ant2 == 2) & (t_idx != 10)] = True          # one sample
    put(truth.ref_ms, "FLAG", flag)
    for tracker in ("smooth", "antenna"):
        out, rep = run(truth, tracker=tracker)
        by_bl = {e["baseline"]: e for e in rep["tracking"]["baselines"]}
        assert by_bl["AP-SM"]["segments"] == 0 and by_bl["AP-SM"]["wrap_events"] == 0
        assert by_bl["AP-PV"]["per_correlation"]["RR"]["segments"] == 1
        tflag = col(truth.target_ms, "FLAG")
        assert tflag[(truth.ant1 == 0) & (truth.ant2 == 1)].all()
        good = ~tflag[:, 0, :]
        assert np.all(np.isfinite(out[:, 0, :][good]))
        sel = (truth.ant1 == 1) & (truth.ant2 == 2)
        e = count_error(truth, out) if tracker == "smooth" else antenna_count_error(truth, out)
        assert np.unique(e[sel, 0]).size == 1 and np.unique(e[sel, 3]).size == 1


def test_station_elevations_from_the_ms_geometry(tmp_path, shared_pair):
    """sin(el) from ANTENNA positions and FIELD direction matches the simulator's truth."""
    from hitops.geometry import station_sin_elevation
    from hitops.simulate.api import simulate

    out = simulate("paper", tmp_path, prefix="el", save_truth=True, duration=600,
                   integration=10, stations="AP,PV,KP", no_noise=True)
    truth = np.load(out["truth"])
    sin_el = station_sin_elevation(str(out["230"]), truth["time"])
    # precession (~0.3 deg since J2000) is ignored: agreement to ~0.01 in sin(el)
    assert np.max(np.abs(sin_el - np.sin(truth["elevation"]))) < 0.01
    fake = shared_pair(PairSpec(n_time=10, corr_types=("RR",)))     # positions off the Earth
    assert station_sin_elevation(str(fake.target_ms), np.array([5.1e9])) is None


def test_fixed_window_max_gap_and_elevation_scaling_options(tmp_path, new_pair):
    truth = new_pair(PairSpec(n_ant=3, n_time=300, corr_types=("RR",), seed=5,
                              troposphere=Troposphere(step_rad=0.1)))
    flag_first_baseline(truth, (100, 108))
    _, rep = run(truth, tracker="smooth", half_window=3, max_gap=5)
    setup = rep["tracking"]["setup"]
    assert setup["half_window"] == 3 and setup["max_gap"] == 5
    assert setup["elevation_scaling"] is False          # synthetic positions: no geometry
    ap_sm = {e["baseline"]: e for e in rep["tracking"]["baselines"]}["AP-SM"]
    assert ap_sm["bridged_gaps"] == 0 and ap_sm["long_gap_segments"] == 1
    # real geometry (hitops simulate): t_c is scaled by sin(el)^(3/5) unless switched off
    from hitops.simulate.api import simulate
    sim = simulate("paper", tmp_path / "sim", prefix="s", duration=300, stations="AP,PV,KP",
                   correlations="RR")
    rep = calibrate_flat(sim["86"], sim["230"], tracker="smooth")
    assert rep["tracking"]["setup"]["elevation_scaling"] is True
    rep = calibrate_flat(sim["86"], sim["230"], tracker="smooth", no_elevation_scaling=True,
                    overwrite=True)
    assert rep["tracking"]["setup"]["elevation_scaling"] is False
    assert rep["tracking"]["setup"]["snr_source"] == "sigma"     # the simulator writes SIGMA


def test_offset_step_per_segment_resolves_a_long_gap(new_pair, caplog):
    """A 300-sample gap: the smooth tracker's best guess across it is wrong (seed 21,
    by one wrap); with a reference column the n0 step runs per segment and fixes it."""
    truth = new_pair(PairSpec(n_ant=3, n_time=900, corr_types=("RR",), seed=21,
                              troposphere=Troposphere(step_rad=0.15)))
    _, first_bl = flag_first_baseline(truth, (300, 600))
    out, rep = run(truth, tracker="smooth")
    valid = col(truth.target_ms, "FLAG")[:, 0, 0] == 0
    e = count_error(truth, out)[:, 0]
    assert np.unique(e[first_bl & valid]).size == 2                 # the guess is wrong
    assert rep["tracking"]["segment_offsets"] == "best guess"
    # a perfect reference calibration of the target (what FF+SC would give)
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    with caplog.at_level("INFO", logger="hitops"):
        out, rep = run(truth, tracker="smooth", offset_reference_column="CORRECTED_DATA")
    assert "resolved by the offset step per segment" in caplog.text
    step = rep["offset_step"]
    assert step["per"] == "segment" and step["applied_to"] == ["pwc"]
    segs = [s for s in step["series"] if s["baseline"] == "AP-SM"]
    assert len(segs) == 2 and {s["segment"] for s in segs} == {0, 1}
    assert segs[0]["k"] != segs[1]["k"]
    assert rep["tracking"]["segment_offsets"].startswith("offset step per segment")
    resid = wrap(np.angle(out[:, 0, 0]) - truth.source_phase[:, 0])
    assert np.max(np.abs(resid[valid])) < 1e-4                       # every n0 and the gap fixed
    # chunked: the same segments and output (k of the second segment may differ: a gap
    # longer than the chunk context continues the count instead of predicting across it)
    out_chunked, rep_chunked = run(truth, tracker="smooth",
                                   offset_reference_column="CORRECTED_DATA", chunk_rows=300)
    assert rep_chunked["chunks"] > 3
    keys = [(s["baseline"], s["scan"], s["segment"]) for s in rep_chunked["offset_step"]["series"]]
    assert keys == [(s["baseline"], s["scan"], s["segment"]) for s in step["series"]]
    assert np.max(np.abs(np.angle(out_chunked[:, 0, 0] * np.conj(out[:, 0, 0]))[valid])) < 1e-5
