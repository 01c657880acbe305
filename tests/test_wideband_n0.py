"""The n0 step across a target window's channels (issue 26), on casatools.simulator layouts.

The pairs (tests/solutions_scene.py's layout): 4 stations, 10 min at 1 s, reference
one window of 16 x 125 MHz, target two windows of 16 x 125 MHz at 228 and 230 GHz
(R_0 = 114/43 and 115/43 against 86 GHz: the lattice 2*pi*eps*k repeats every 43);
every channel carries exp(2*pi*i*nu_k*(L_p - L_q)/c) of a per-station excess
path.  Here the stations' paths differ by up to 13 cm at the start (38 turns of the
86-GHz phase), so PWC, counting from n'(t0) = 0, is off by n0 = up to 38 turns.  One
channel cannot tell n0 from n0 - 43 at R = 230/86 (the same 2*pi*eps*n0); the
window's channels can, because a wrong k leaves a phase slope 2*pi*(nu_j - nu_0)*k/nu_ref
across it.  The truth is the path: after FPT and the n0 step with a point model, every
channel of every baseline must have phase 0.  The plausible wrong implementation, the
step on the window centre's phase alone (what calibrate did before), fails the same check.

Last section: PWC and CFPT on a multi-channel target take the rows' validity instead
of the target's delay-fit reduction, and write the same bytes as with it.
"""

from __future__ import annotations

import numpy as np
import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate.channels import ChannelPlan
from hitops.calibrate.n0.baseline import WindowRatios, choose_channel_offset, choose_offset
from hitops.calibrate.n0.lattice import solve_lattice

from solutions_scene import C_LIGHT, excess_path, lay_out, write_path_phases

STATIONS = ("PV", "PB", "AP", "GL")
#: per-station excess path at the start, metres: baselines up to 38 turns at 86 GHz
START_PATH_M = np.array([0.0, 0.091, -0.043, 0.022])
#: target windows' centres: both ratios to 86 GHz are multiples of 1/43
TARGET_CENTRES_HZ = (228.0e9, 230.0e9)


def _pair(root, ref_centre_hz: float):
    from casacore import tables as pt

    root.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = root / "ref.ms", root / "target.ms"
    scans = (("M87", 0.0, 600.0),)
    lay_out(ref_ms, (ref_centre_hz,), scans, "2023/04/10/03:00:00", STATIONS)
    lay_out(target_ms, TARGET_CENTRES_HZ, scans, "2023/04/10/03:00:00", STATIONS)
    with pt.table(str(ref_ms), ack=False) as t:
        times = np.unique(t.getcol("TIME"))
    path = excess_path(times, len(STATIONS), seed=3, scale_m=0.004) + START_PATH_M
    write_path_phases(ref_ms, times, path)
    write_path_phases(target_ms, times, path)
    return ref_ms, target_ms, path


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Reference at 86 GHz: R_0 = 227.1/86 and 229.1/86."""
    return _pair(tmp_path_factory.mktemp("n0-wide"), 86.0e9)


@pytest.fixture(scope="module")
def integer_pair(tmp_path_factory):
    """Reference at 76.67 GHz: R_0 = 3 exactly for the 230-GHz window."""
    return _pair(tmp_path_factory.mktemp("n0-integer"), 230.0e9 / 3)


def _copy(ms, directory):
    import shutil

    directory.mkdir(parents=True, exist_ok=True)
    out = directory / ms.name
    shutil.copytree(ms, out)
    return out


def channel_phases(ms, column="PWC_DATA"):
    """{(ant1, ant2, window): (n_chan, n_corr) phase of the whole-track vector mean} and the
    smallest coherence of any channel."""
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        data, flag = t.getcol(column), t.getcol("FLAG")
        a1, a2, ddid = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("DATA_DESC_ID")
    phases, coherence = {}, 1.0
    for key in sorted(set(zip(a1, a2, ddid))):
        rows = (a1 == key[0]) & (a2 == key[1]) & (ddid == key[2])
        ok = ~flag[rows]
        unit = np.where(ok, data[rows] / np.where(ok, np.abs(data[rows]), 1), 0)
        mean = unit.sum(axis=0) / np.maximum(ok.sum(axis=0), 1)
        phases[key] = np.angle(mean)
        coherence = min(coherence, float(np.abs(mean).min()))
    return phases, coherence


def worst_phase(ms) -> float:
    phases, coherence = channel_phases(ms)
    assert coherence >= 0.999
    return max(float(np.abs(p).max()) for p in phases.values())


def centre_channel_only(monkeypatch):
    """The wrong implementation: the n0 step on the window centre's phase alone."""
    monkeypatch.setattr(ChannelPlan, "across_channels", property(lambda self: False))


@pytest.mark.slow
def test_the_paths_need_more_than_half_a_lattice_period(pair):
    # the premise: some baseline starts more than 21 turns of the 86-GHz phase away
    _, _, path = pair
    turns = 86.0e9 * (path[0][:, None] - path[0][None, :]) / C_LIGHT
    assert np.abs(turns).max() > 30


@pytest.mark.slow
@pytest.mark.parametrize("tracker", ["count", "smooth", "antenna"])
def test_the_step_across_the_channels_finds_the_true_offset(pair, tmp_path, monkeypatch,
                                                            tracker):
    ref_ms, target_ms, _ = pair
    target = _copy(target_ms, tmp_path / "all")
    report = calibrate_flat(str(ref_ms), str(target), method="pwc", tracker=tracker,
                       offset_model="point", no_verdict=True)
    assert worst_phase(target) < 1e-3          # every channel of every baseline at phase 0
    entries = [e for e in report["groups"][0]["offset_step"]["series"] if e.get("samples")]
    assert max(abs(e["k"]) for e in entries) > 21     # beyond one channel's lattice period
    # the centre channel alone chooses k - 43 where |k| > 21: right at the window centre,
    # radians off at its edges
    wrong = _copy(target_ms, tmp_path / "centre")
    with monkeypatch.context() as m:
        centre_channel_only(m)
        calibrate_flat(str(ref_ms), str(wrong), method="pwc", tracker=tracker,
                  offset_model="point", no_verdict=True)
    phases, _ = channel_phases(wrong)
    assert max(float(np.abs(p).max()) for p in phases.values()) > 1.0
    at_centre = [np.angle(np.exp(1j * p[7]) + np.exp(1j * p[8])) for p in phases.values()]
    assert np.abs(at_centre).max() < 1e-3


@pytest.mark.slow
def test_integer_ratio_at_the_centre_still_needs_the_step_across_the_window(integer_pair,
                                                                           tmp_path,
                                                                           monkeypatch):
    # R_0 = 3 for the second target window: the centre channel carries no n0 offset, but
    # channel j carries 2*pi*(R_j - 3)*n0, a slope of n0*B/nu_ref turns across the window
    ref_ms, target_ms, _ = integer_pair
    target = _copy(target_ms, tmp_path / "all")
    report = calibrate_flat(str(ref_ms), str(target), method="pwc", tracker="count",
                       offset_model="point", no_verdict=True)
    assert report["groups"][1]["channels"]["target_centre_hz"] == 230.0e9
    assert worst_phase(target) < 1e-3
    skipped = _copy(target_ms, tmp_path / "skipped")
    with monkeypatch.context() as m:
        centre_channel_only(m)         # the step skipped as "integer R" on window 1
        calibrate_flat(str(ref_ms), str(skipped), method="pwc", tracker="count",
                  offset_model="point", no_verdict=True)
    phases, _ = channel_phases(skipped)
    window1 = [p for key, p in phases.items() if key[2] == 1]
    assert max(float(np.abs(p).max()) for p in window1) > 0.3


# ---------------------------------------------------------------- the choice itself, pure
REF_HZ = 86.0e9
WINDOW_HZ = 230.0e9 + (np.arange(16) - 7.5) * 125e6       # R_0 = 115/43


def window_ratios(freqs=WINDOW_HZ) -> WindowRatios:
    centre = float(np.mean(freqs)) / REF_HZ
    return WindowRatios(np.asarray(freqs) / REF_HZ, centre, centre - np.floor(centre))


def sums_for(window: WindowRatios, n0: int, error_deg: float = 0.0, samples: int = 100):
    """z_j of a series whose count is n0 turns off, the reference good to error_deg."""
    turns = window.ratios * n0
    return samples * np.exp(2j * np.pi * (turns - np.floor(turns)) + 1j * np.deg2rad(error_deg))


@pytest.mark.parametrize("n0", [-38, -22, 0, 5, 21, 30, 50])
def test_the_channels_choose_the_true_offset_where_the_centre_cannot(n0):
    window = window_ratios()
    z = sums_for(window, n0, error_deg=1.5)
    choice = choose_channel_offset(z, 1600, window, max_k=50, ambiguity_deg=2.0)
    assert choice.k == n0 and not choice.ambiguous
    assert choice.runner_up_residual_deg - choice.residual_deg > 5
    # one channel at the centre: k and k +- 43 are the same offset; the smaller |k| wins
    centre = complex(np.exp(2j * np.pi * window.eps * n0 + 1j * np.deg2rad(1.5)))
    single = choose_offset(centre, 1, window.eps, max_k=50, ambiguity_deg=2.0)
    assert single.k == (n0 if abs(n0) <= 21 else n0 - 43 * np.sign(n0))


def test_one_channel_scores_as_the_centre_lattice():
    # a one-channel window reads the same residual as the old rule
    window = WindowRatios(np.array([227.1e9 / REF_HZ]), 227.1e9 / REF_HZ,
                          227.1e9 / REF_HZ - 2)
    z = np.array([np.exp(1j * 0.3)])
    across = choose_channel_offset(z, 1, window, max_k=50, ambiguity_deg=2.0)
    centre = choose_offset(complex(z[0]), 1, window.eps, max_k=50, ambiguity_deg=2.0)
    assert across.k == centre.k
    assert across.residual_deg == pytest.approx(centre.residual_deg, abs=1e-6)


def test_integer_ratio_at_the_centre_is_told_apart_by_the_edges():
    freqs = 230.0e9 + (np.arange(16) - 7.5) * 125e6
    window = WindowRatios(freqs / (230.0e9 / 3), 3.0, 0.0)
    choice = choose_channel_offset(sums_for(window, 7), 1600, window, 50, 2.0)
    assert choice.k == 7 and choice.offset_deg == 0.0
    assert choice.runner_up_residual_deg == pytest.approx(2.7055, abs=1e-3)   # k +- 1


def test_the_antenna_lattice_across_channels_finds_every_antenna():
    # 6 antennas, every baseline; per-antenna counts off by up to 40 turns
    window = window_ratios()
    truth = np.array([0, 40, -31, 23, -44, 12])
    a, b = np.triu_indices(truth.size, 1)
    errors = 2.0 * np.sin(np.arange(a.size))                  # the reference's, degrees
    z = np.array([sums_for(window, int(truth[p] - truth[q]), e)
                  for p, q, e in zip(a, b, errors)])
    solution = solve_lattice(truth.size, a, b, z, np.full(a.size, 1600), window.eps, 50,
                             gauge_order=[0], window=window)
    assert solution.k.tolist() == truth.tolist()
    # the same series at the window centre alone: the lattice folds k by 43
    centre = WindowRatios(np.array([window.centre]), window.centre, window.eps)
    z_centre = np.array([sums_for(centre, int(truth[p] - truth[q]), e)[0]
                         for p, q, e in zip(a, b, errors)])
    folded = solve_lattice(truth.size, a, b, z_centre, np.full(a.size, 100), window.eps, 50,
                           gauge_order=[0])
    assert folded.k.tolist() != truth.tolist()
    assert np.all((folded.k - truth) % 43 == 0)


# ------------------------------------------- PWC and CFPT without the target's reduction
def test_row_validity_is_the_reductions_validity():
    from hitops.calibrate.channels import reduce_rows
    from hitops.kernels.wideband import row_validity

    rng = np.random.default_rng(2)
    shape = (400, 16, 4)
    data = np.exp(1j * rng.uniform(-np.pi, np.pi, shape)).astype(np.complex64)
    data[rng.random(shape) < 0.2] = 0
    data[rng.random(shape) < 0.1] = np.nan
    flag = rng.random(shape) < 0.5
    flag[:40] = True                                    # rows with every channel flagged
    flag_row = rng.random(400) < 0.1
    _, reduced_ok = reduce_rows(data, ~flag & ~flag_row[:, None, None], WINDOW_HZ, 230.0e9)
    valid = row_validity(data, flag, flag_row)
    assert np.array_equal(valid, reduced_ok)
    assert 0.2 < valid.mean() < 0.95


@pytest.mark.slow
def test_pwc_and_cfpt_write_the_same_bytes_without_the_target_reduction(pair, tmp_path,
                                                                       monkeypatch):
    from casacore import tables as pt

    import hitops.calibrate.chunk_read as chunk_read

    ref_ms, target_ms, _ = pair
    columns = {}
    for name in ("validity", "reduced"):
        target = _copy(target_ms, tmp_path / name)
        with pt.table(str(target), readonly=False, ack=False) as t:
            flag = t.getcol("FLAG")
            rng = np.random.default_rng(5)
            flag |= rng.random(flag.shape) < 0.3
            flag[rng.random(flag.shape[0]) < 0.05] = True
            t.putcol("FLAG", flag)
        with monkeypatch.context() as m:
            if name == "reduced":       # what calibrate did before: the delay fit, always
                m.setattr(chunk_read, "target_rows",
                          lambda data, flag, flag_row, channels, phase_needed:
                          chunk_read.reduce(data, flag, flag_row, channels, "tgt"))
            calibrate_flat(str(ref_ms), str(target), method="pwc,cfpt", tracker="antenna",
                      chunk_rows=2000, no_verdict=True)
        with pt.table(str(target), ack=False) as t:
            columns[name] = [t.getcol(c).tobytes() for c in ("PWC_DATA", "CFPT_DATA", "FLAG")]
    assert columns["validity"] == columns["reduced"]
