"""The n0 offset step against a model (issue 16): ``--offset-model point|COLUMN``.

With ``--tracker antenna`` the integers are solved per antenna and segment on the
2 pi eps k lattice with every baseline at once (hitops.calibrate.n0.lattice); with the
baseline trackers the step falls back to the per-baseline choice against the model.
Scenes from hitops.testing.make_pair with ``ref_offset_scale=0`` (a
purely antenna-based reference band, as a point source gives), so a noiseless
output with the right integers equals the source phase exactly.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Signal, Troposphere, add_column, wrap
from hitops.errors import InputError
from ms_columns import col, put  # tests/ is on sys.path (rootdir-relative)

EPS = 230.0 / 86.0 - 2


def run(truth, column="OUT", **kw):
    rep = calibrate_flat(truth.ref_ms, truth.target_ms, output_column=column, overwrite=True, **kw)
    return col(truth.target_ms, column), rep


def late_station_pair(new_pair):
    """4 stations, GL (index 3) joins the reference band after 250 s (tests/test_antenna.py's
    scene, with a purely antenna-based reference band)."""
    truth = new_pair(PairSpec(n_ant=4, n_time=700, seed=11, corr_types=("RR", "LL"),
                              troposphere=Troposphere(step_rad=0.12, drift_rad=0.06,
                                                      phase_offset_rad=1.0, ref_offset_scale=0.0)))
    flag = col(truth.ref_ms, "FLAG")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    flag[((truth.ant1 == 3) | (truth.ant2 == 3)) & (t_idx < 250)] = True
    put(truth.ref_ms, "FLAG", flag)
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    return truth


def lattice_integer(y):
    """e in [-21, 21] with 2 pi eps e = y (mod 2 pi), per element."""
    k = np.arange(43)
    e = k[np.argmin(np.abs(wrap(np.asarray(y)[..., None] - wrap(2 * np.pi * EPS * k))), axis=-1)]
    return np.where(e > 21, e - 43, e)


def closures(truth, phase):
    """Closure phases (rad) of per-row phases over every triangle, per time and correlation."""
    n_ant = int(max(truth.ant1.max(), truth.ant2.max())) + 1
    times = np.unique(truth.time)
    t_idx = np.searchsorted(times, truth.time)
    grid = np.full((n_ant, n_ant, times.size, phase.shape[1]), np.nan)
    grid[truth.ant1, truth.ant2, t_idx] = phase
    out = []
    for p, q, r in itertools.combinations(range(n_ant), 3):
        out.append(grid[p, q] + grid[q, r] - grid[p, r])
    return np.array(out)


def test_late_station_true_integers_and_closures_kept(new_pair):
    truth = late_station_pair(new_pair)
    before, rep0 = run(truth, column="NOSTEP", tracker="antenna", refant="PV")
    flag = col(truth.target_ms, "FLAG")[:, 0, :]
    valid = ~flag
    resid0 = wrap(np.angle(before[:, 0, :]) - truth.source_phase)
    assert np.degrees(np.abs(resid0[valid])).max() > 100      # GL's baselines carry 2 pi eps k
    # the truth: GL's count error relative to PV, read off the output without the step
    gl_pv = (truth.ant1 == 2) & (truth.ant2 == 3) & valid[:, 0]
    k_true = np.unique(lattice_integer(resid0[gl_pv, 0]))
    assert k_true.size == 1 and k_true[0] != 0
    after, rep = run(truth, column="STEP", tracker="antenna", refant="PV",
                     offset_model="MODEL_DATA")
    assert np.array_equal(col(truth.target_ms, "FLAG")[:, 0, :], flag)
    resid = wrap(np.angle(after[:, 0, :]) - truth.source_phase)
    assert np.max(np.abs(resid[valid])) < 1e-3        # every baseline and sample (complex64)
    step = rep["offset_step"]
    assert step["solve"] == "antenna lattice" and step["model"] == "MODEL_DATA"
    assert step["per"] == "segment" and step["applied_to"] == ["pwc"]
    by_ant = {(e["antenna"], e["correlation"]): e for e in step["antennas"]}
    assert len(by_ant) == 8
    for c in ("RR", "LL"):
        assert by_ant[("PV", c)]["reference"] and by_ant[("PV", c)]["k"] == 0
        # PV-GL carries 2 pi eps e; the step adds 2 pi eps (k_PV - k_GL) = -2 pi eps e
        assert by_ant[("GL", c)]["k"] == k_true[0]
        assert by_ant[("AP", c)]["k"] == 0 and by_ant[("SM", c)]["k"] == 0
        for e in (by_ant[(a, c)] for a in ("AP", "SM", "PV", "GL")):
            assert e["residual_deg"] < 0.05 and e["margin_deg"] > 8.0 and not e["ambiguous"]
    assert [s["method"] for s in step["solves"]] == ["exhaustive", "exhaustive"]
    assert all(s["coherence"] > 0.9999 for s in step["solves"])
    # closure phases: the per-baseline integers close exactly (so the phase added by the
    # step closes to float64 rounding), and the written output keeps the target's closures
    # to the precision of its complex64 storage
    n_ant = 4
    d = {}
    for e in step["series"]:
        d[(e["baseline"], e["correlation"])] = e["k"]
    names = ["AP", "SM", "PV", "GL"]
    for c in ("RR", "LL"):
        for p, q, r in itertools.combinations(range(n_ant), 3):
            k_close = (d[(f"{names[p]}-{names[q]}", c)] + d[(f"{names[q]}-{names[r]}", c)]
                       - d[(f"{names[p]}-{names[r]}", c)])
            assert k_close == 0
            assert abs(math.remainder(2 * math.pi * EPS * k_close, 2 * math.pi)) < 1e-9
    ok_rows = valid.all(axis=1)
    cl0 = closures(truth, np.where(ok_rows[:, None], np.angle(before[:, 0, :]), np.nan))
    cl1 = closures(truth, np.where(ok_rows[:, None], np.angle(after[:, 0, :]), np.nan))
    fin = np.isfinite(cl0)
    assert fin.sum() > 1000
    assert np.max(np.abs(wrap(cl1[fin] - cl0[fin]))) < 2e-6


def test_point_model_and_chunked_runs_agree(new_pair):
    """--offset-model point on a point source at the phase centre; several scans; the
    one-chunk run (first pass kept, shifted) equals the chunked run (two passes)."""
    truth = new_pair(PairSpec(n_ant=5, n_time=900, n_scans=3, seed=4, corr_types=("RR", "LL"),
                              troposphere=Troposphere(step_rad=0.1, drift_rad=0.05,
                                                      phase_offset_rad=1.3, ref_offset_scale=0.0),
                              signal=Signal(sigma_ref=0.05, sigma_target=0.05)))
    data = col(truth.target_ms, "DATA")
    put(truth.target_ms, "DATA", (data * np.exp(-1j * truth.source_phase)[:, None, :])
        .astype(np.complex64))                         # the source: a point at the centre
    out, rep = run(truth, tracker="antenna", offset_model="point")
    valid = ~col(truth.target_ms, "FLAG")[:, 0, :]
    resid = np.degrees(np.abs(wrap(np.angle(out[:, 0, :]))))
    # thermal noise only (R x reference noise + target noise, a few degrees)
    assert np.median(resid[valid]) < 5
    for a1, a2 in set(zip(truth.ant1.tolist(), truth.ant2.tolist())):
        sel = (truth.ant1 == a1) & (truth.ant2 == a2)
        for c in range(2):
            x = out[sel, 0, c][valid[sel, c]]
            assert abs(np.mean(x / np.abs(x))) > 0.99          # whole-track coherence
    step = rep["offset_step"]
    assert step["model"] == "point" and len(step["solves"]) == 3 * 2
    assert rep["chunks"] == 1 and "offset_solve" in rep["timings_s"]
    out_chunked, rep_chunked = run(truth, column="OUT2", tracker="antenna", offset_model="point",
                                   chunk_rows=1000)
    assert rep_chunked["chunks"] > 3
    assert [(e["antenna"], e["correlation"], e["scan"], e["k"]) for e in step["antennas"]] == \
        [(e["antenna"], e["correlation"], e["scan"], e["k"])
         for e in rep_chunked["offset_step"]["antennas"]]
    assert np.max(np.abs(np.angle(out_chunked[:, 0, :] * np.conj(out[:, 0, :]))[valid])) < 1e-5
    # without the step the same output carries the constants, and the run says so last
    no_step, rep_ns = run(truth, column="OUT3", tracker="antenna")
    assert rep_ns["offset_step"]["warning"] and "OUT3" in rep_ns["offset_step"]["warning"]
    assert step["warning"] is None


def test_baseline_trackers_fall_back_to_the_per_baseline_choice(new_pair):
    truth = new_pair(PairSpec(n_time=300, seed=1,
                              troposphere=Troposphere(phase_offset_rad=2.5, ref_offset_scale=0.0)))
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    for tracker in ("count", "smooth"):
        out, rep = run(truth, tracker=tracker, offset_model="MODEL_DATA")
        assert np.max(np.abs(wrap(np.angle(out[:, 0, :]) - truth.source_phase))) < 1e-4
        step = rep["offset_step"]
        assert step["solve"] == "baseline" and step["antennas"] == [] and step["solves"] == []
        assert step["per"] == ("scan" if tracker == "count" else "segment")
        assert any(e["k"] != 0 for e in step["series"])


def test_no_step_warning_is_among_the_last_lines(new_pair, caplog):
    truth = new_pair(PairSpec(n_time=100, seed=2, corr_types=("RR",)))
    with caplog.at_level("INFO", logger="hitops"):
        calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    last = [r for r in caplog.records if r.name.startswith("hitops")][-2:]
    assert "wrote PWC_DATA, CFPT_DATA" in last[0].getMessage()
    assert last[1].levelname == "WARNING"
    msg = last[1].getMessage()
    assert "PWC_DATA carries a constant 2 pi eps n0 per baseline" in msg
    assert "--offset-model point" in msg and "self-calibrate" in msg
    report = json.loads((truth.target_ms.parent / "target.ms.hitops-calibrate.json").read_text())
    assert report["offset_step"]["warning"] == msg
    caplog.clear()
    with caplog.at_level("INFO", logger="hitops"):
        calibrate_flat(truth.ref_ms, truth.target_ms, method="cfpt", overwrite=True)
    assert "no n0 offset step ran" not in caplog.text            # CFPT has no n0
    with caplog.at_level("INFO", logger="hitops"):
        calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", ratio=3.0, overwrite=True)
    assert "no n0 offset step ran" not in caplog.text            # integer R has none


@pytest.mark.parametrize("kwargs, match", [
    (dict(offset_model="point", offset_reference_column="DATA"), "give one"),
    (dict(offset_model="MODEL_DATA"), "MODEL_DATA"),
])
def test_bad_model_options_leave_the_set_unchanged(new_pair, kwargs, match):
    truth = new_pair(PairSpec(n_time=50, seed=3, corr_types=("RR",)))
    before = set(pt.table(str(truth.target_ms), ack=False).colnames())
    with pytest.raises(Exception, match=match):
        calibrate_flat(truth.ref_ms, truth.target_ms, **kwargs)
    assert set(pt.table(str(truth.target_ms), ack=False).colnames()) == before


def test_model_column_is_not_an_output(new_pair):
    truth = new_pair(PairSpec(n_time=50, seed=3, corr_types=("RR",)))
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    with pytest.raises(InputError, match="input or flag column"):
        calibrate_flat(truth.ref_ms, truth.target_ms, offset_model="MODEL_DATA",
                  output_column="MODEL_DATA", overwrite=True)


# ----------------------------------------------------------------------------- both hands

def test_reference_column_with_antenna_tracker_solves_on_the_lattice(new_pair):
    """--offset-reference-column with --tracker antenna: per antenna on the lattice against
    the reference column (as --offset-model does against a model), both hands tied."""
    truth = late_station_pair(new_pair)
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    before, _ = run(truth, column="NOSTEP", tracker="antenna", refant="PV")
    valid = ~col(truth.target_ms, "FLAG")[:, 0, :]
    resid0 = wrap(np.angle(before[:, 0, :]) - truth.source_phase)
    gl_pv = (truth.ant1 == 2) & (truth.ant2 == 3) & valid[:, 0]
    k_true = np.unique(lattice_integer(resid0[gl_pv, 0]))
    assert k_true.size == 1 and k_true[0] != 0
    after, rep = run(truth, column="STEP", tracker="antenna", refant="PV",
                     offset_reference_column="CORRECTED_DATA")
    resid = wrap(np.angle(after[:, 0, :]) - truth.source_phase)
    assert np.max(np.abs(resid[valid])) < 1e-3
    step = rep["offset_step"]
    assert step["solve"] == "antenna lattice" and step["column"] == "CORRECTED_DATA"
    by_ant = {(e["antenna"], e["correlation"]): e for e in step["antennas"]}
    for c in ("RR", "LL"):
        assert by_ant[("GL", c)]["k"] == k_true[0] and by_ant[("PV", c)]["reference"]
        # the hands were solved together, each antenna tied to its other hand
        assert all(by_ant[(a, c)]["hands"] == "RR+LL" and by_ant[(a, c)]["tied"]
                   for a in ("AP", "SM", "PV", "GL"))
    assert {s["hands"] for s in step["solves"]} == {"RR+LL"}
    # the per-baseline integers close on every triangle
    d = {(e["baseline"], e["correlation"]): e["k"] for e in step["series"]}
    names = ["AP", "SM", "PV", "GL"]
    for c in ("RR", "LL"):
        for p, q, r in itertools.combinations(range(4), 3):
            assert (d[(f"{names[p]}-{names[q]}", c)] + d[(f"{names[q]}-{names[r]}", c)]
                    - d[(f"{names[p]}-{names[r]}", c)]) == 0


def _hands_scene(n_scans=4, n_per_scan=10, j=(0, 2, -1), ref_rl=(0.0, 0.5, -0.4)):
    """Tracked antenna phases of two hands (RR, LL) whose count errors differ by j per
    antenna, plus a constant instrumental R-L phase ref_rl (rad)."""
    n_ant, n_time = 3, n_scans * n_per_scan
    rng = np.random.default_rng(5)
    common = np.cumsum(rng.normal(0, 0.2, (n_ant, n_time)), axis=1)
    common[0] = 0.0                                    # the reference antenna
    phase = np.zeros((n_ant, 2, n_time))
    phase[:, 0] = common
    phase[:, 1] = common - np.asarray(ref_rl)[:, None] - 2 * np.pi * np.asarray(j)[:, None]
    segment = np.zeros((n_ant, 2, n_time), np.int64)
    scan_of_time = np.repeat(np.arange(n_scans), n_per_scan)
    return {"phase": phase, "segment": segment, "scan_of_time": scan_of_time}


def test_hand_ties_recover_j_and_refuse_a_split_segment():
    from hitops.calibrate.n0.hands import hand_ties

    hands = _hands_scene()
    ties = hand_ties(hands["phase"], hands["segment"], hands["scan_of_time"], 0, 1)
    assert {(s, p): jt for (s, p, a, b), (jt, n) in ties.items()} == \
        {(s, p): jp for s in range(4) for p, jp in enumerate((0, 2, -1))}
    assert all(n == 10 for _, n in ties.values())
    # a slip in one hand half-way through scan 2 of antenna 1: no tie there
    phase = hands["phase"].copy()
    phase[1, 1, 25:30] += 2 * np.pi
    ties = hand_ties(phase, hands["segment"], hands["scan_of_time"], 0, 1)
    assert (2, 1, 0, 0) not in ties and (1, 1, 0, 0) in ties and (2, 2, 0, 0) in ties


def test_both_hands_outvote_one_hand_off_its_lattice_point():
    """Per scan, one hand of antenna 1 measures its offset beyond the midpoint between
    lattice points (4.6 deg, half the spacing is 4.19 deg) and the other hand 3 deg the
    other way: alone, that hand picks the neighbouring point; tied (k_RR - k_LL = j from
    the reference band, LL's constant instrumental phase of 100 deg on antenna 2 measured
    over the track and removed), every integer is the true one."""
    from hitops.calibrate.n0.antenna import LatticeProblem, antenna_offsets
    from hitops.calibrate.n0.hands import HandPhases
    from hitops.tracking.state import PAIR_KEY

    two_pi_eps = 2 * np.pi * EPS
    j = np.array([0, 2, -1])
    m_rr = {0: np.array([0, 5, -7]), 1: np.array([0, -11, 3]), 2: np.array([0, 1, 9]),
            3: np.array([0, -4, -2])}
    bias = {0: (4.6, -3.0), 1: (-3.0, 4.6), 2: (1.0, 1.0), 3: (0.0, 0.0)}   # antenna 1, deg
    beta_ll = np.radians([0.0, 0.0, 100.0])
    ant1, ant2 = np.array([0, 0, 1]), np.array([1, 2, 2])
    seg_sums = {}
    key_of = lambda s: s * (1 << 32) + 0 * PAIR_KEY + 0
    for s in range(4):
        for c in (0, 1):
            m = m_rr[s] - (j if c == 1 else 0)             # k_RR - k_LL = j
            cst = np.radians([0.0, bias[s][c], 0.0]) + (beta_ll if c == 1 else 0.0)
            for b, (p, q) in enumerate(zip(ant1, ant2)):
                z = 600 * np.exp(1j * (two_pi_eps * (m[p] - m[q]) - (cst[p] - cst[q])))
                seg_sums[(b, c, key_of(s))] = (z, 600)
    problem = LatticeProblem(ant1=ant1, ant2=ant2, antenna_names=["AP", "SM", "PV"],
                             baseline_names=["AP-SM", "AP-PV", "SM-PV"], corr_names=["RR", "LL"],
                             scans=np.arange(1, 5), eps=EPS, max_k=50, ambiguity_deg=2.0,
                             refants=(0,))

    def wrong_segments(result):
        bad = set()
        for e in result.antennas:
            truth = m_rr[e["scan"] - 1][e["antenna_index"]] - (j[e["antenna_index"]]
                                                                 if e["correlation"] == "LL" else 0)
            if abs(math.remainder(two_pi_eps * (e["k"] - truth), 2 * np.pi)) > 1e-6:
                bad.add((e["scan"], e["correlation"]))
        return bad

    alone = antenna_offsets(seg_sums, {0, 1}, problem)
    # (LL alone also rounds its 100 deg instrumental phase onto the lattice: not the truth)
    assert {w for w in wrong_segments(alone) if w[1] == "RR"} == {(1, "RR")}
    tied = antenna_offsets(seg_sums, {0, 1}, problem, hands=HandPhases(**_hands_scene()))
    assert wrong_segments(tied) == set()
    assert all(e["hands"] == "RR+LL" and e["tied"] for e in tied.antennas)
    # LL keeps its instrumental phase, the same in every scan (no lattice step between scans)
    ap_pv = [e["residual_deg"] for e in tied.series
             if e["correlation"] == "LL" and e["baseline"] == "AP-PV"]
    assert len(ap_pv) == 4 and np.allclose(ap_pv, 100.0, atol=1e-6)
