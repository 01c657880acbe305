"""calibrate --calibrator-field: the instrumental term after FPT, solved on a calibrator.

Truth from outside the code under test: hitops simulate writes a target and a
calibrator in alternating scans through one troposphere, with per-station, per-band
instrumental phases, delays and drifts from the scene; its truth file holds them, and
the term FPT leaves is the paper's Phi_inst - R*phi_inst, per channel.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.simulate import simulate
from hitops.simulate.scene import load_scene_mapping

REF_GHZ, TGT_GHZ = 86.0, 230.0
#: the packaged scene (hitops/scenes/phaseref.yml) cut to 20 minutes without noise
SCENE = load_scene_mapping("phaseref")[0]
SCENE["observation"]["duration"] = 1200
SCENE["corruptions"]["noise"] = False
#: what the step must reach on every target baseline, noise-free
COHERENCE = 0.99
#: solved against true per-antenna terms (noise-free; the scan average of a drift
#: against its value at the scan's mean time, and the solve's convergence)
PHASE_TOL_DEG, DELAY_TOL_PS = 0.1, 0.5


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("phase-ref")
    paths = simulate(SCENE, out, save_truth=True)
    return paths


def _copy(pair, tmp_path):
    ref, tgt = tmp_path / "ref.ms", tmp_path / "tgt.ms"
    shutil.copytree(pair["86"], ref)
    shutil.copytree(pair["230"], tgt)
    return str(ref), str(tgt)


def _target_coherence(ms: str, column: str = "PWC_DATA", field: int = 0) -> np.ndarray:
    """Whole-track coherence |mean exp(i phase)| over every channel and parallel hand of
    each baseline of ``field``."""
    with pt.table(ms, ack=False) as t:
        sel = t.getcol("FIELD_ID") == field
        a1, a2 = t.getcol("ANTENNA1")[sel], t.getcol("ANTENNA2")[sel]
        data, flag = t.getcol(column)[sel], t.getcol("FLAG")[sel]
    out = []
    for p, q in sorted(set(zip(a1.tolist(), a2.tolist()))):
        v = data[(a1 == p) & (a2 == q)]
        ok = ~flag[(a1 == p) & (a2 == q)] & (np.abs(v) > 0)
        if not ok.any():    # a baseline wholly flagged has no coherence to give
            continue
        out.append(abs((v[ok] / np.abs(v[ok])).sum()) / ok.sum())
    return np.array(out)


def test_calibrator_step_restores_the_target(pair, tmp_path):
    ref, tgt = _copy(pair, tmp_path / "a")
    calibrate_flat(ref, tgt, overwrite=True, no_verdict=True)
    before = _target_coherence(tgt)
    ref2, tgt2 = _copy(pair, tmp_path / "b")
    report = calibrate_flat(ref2, tgt2, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    after = _target_coherence(tgt2)
    assert before.min() < 0.5, before          # FPT alone: the instrumental term remains
    assert after.min() >= COHERENCE, after
    assert np.abs(_target_phases(tgt2)).max() < 1.0
    entry = report["phase_referencing"]["methods"]["PWC_DATA"][0]
    assert entry["target_rows"] > 0 and entry["target_rows_flagged"] == 0
    # every calibrator scan of the set (4 in 20 min of the scene's 5-min cycle)
    assert len(entry["scans"]) == _calibrator_scans(tgt2) == 4
    written = json.loads(open(report["report_path"]).read())
    assert written["phase_referencing"]["calibrator_field"] == "3C273"
    steps = {g["field"]: g["offset_step"] for g in written["groups"]}
    assert steps["M87"]["warning"] is None and "3C273" in steps["M87"]["note"]


def test_solutions_match_the_scene(pair, tmp_path):
    """Per scan and antenna: Phi_inst(nu_0) - (nu_0/nu_ref) phi_inst and the delay
    tau_inst - phi_inst / (2 pi nu_ref), both referred to the reference antenna."""
    ref, tgt = _copy(pair, tmp_path)
    report = calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True, refant="PB")
    window = report["phase_referencing"]["methods"]["PWC_DATA"][0]
    assert window["refant"] == "PB"
    truth = np.load(pair["truth"])
    stations, times = list(truth["stations"]), truth["time"]
    nu0, nu_ref = window["freq_hz"], REF_GHZ * 1e9
    big, small = truth["inst_phase_230"], truth["inst_phase_86"]
    delay = truth["inst_delay_230"]
    phase = big + 2 * np.pi * (nu0 - TGT_GHZ * 1e9) * delay - (nu0 / nu_ref) * small
    delay = delay - small / (2 * np.pi * nu_ref)
    r = stations.index("PB")
    checked = 0
    # up to one integer n per antenna and hand for the whole track (2 pi R_0 n and
    # n / nu_ref: the first calibrator scan's wraps, which no data can tell apart)
    integer = {}
    for j, scan in enumerate(window["scans"]):
        in_scan = (truth["field_id"] == 1) & (np.abs(times - scan["time"]) < 31)
        for a, code in enumerate(stations):
            want_phase = np.angle(np.mean(np.exp(1j * (phase[a, in_scan] - phase[r, in_scan]))))
            want_delay = np.mean(delay[a, in_scan] - delay[r, in_scan])
            for hand in ("R", "L"):
                got = window["antennas"][code][hand]
                n = integer.setdefault((code, hand), int(round(
                    (got["delay_ns"][j] * 1e-9 - want_delay) * nu_ref)))
                want = want_phase + 2 * np.pi * (nu0 / nu_ref) * n
                err = np.angle(np.exp(1j * (np.radians(got["phase_deg"][j]) - want)))
                assert abs(np.degrees(err)) < PHASE_TOL_DEG, (code, j)
                assert abs(got["delay_ns"][j] * 1e-9 - want_delay - n / nu_ref) \
                    < DELAY_TOL_PS * 1e-12
                checked += 1
    assert checked == _calibrator_scans(tgt) * 5 * 2 == 40
    # the truth is not trivially matched: with R replaced by its integer part r the
    # expected phases move far beyond the tolerance
    wrong = big - 2 * small
    assert np.degrees(np.abs(np.angle(np.exp(1j * (wrong - phase))))).max() > 10 * PHASE_TOL_DEG


def _calibrator_scans(ms: str) -> int:
    """How many distinct SCAN_NUMBERs the calibrator (FIELD_ID 1) has in ``ms``."""
    with pt.table(ms, ack=False) as t:
        return int(np.unique(t.getcol("SCAN_NUMBER")[t.getcol("FIELD_ID") == 1]).size)


def _target_phases(ms: str, column: str = "PWC_DATA") -> np.ndarray:
    """Phase (deg) of the vector mean of each target baseline (every channel and hand)."""
    with pt.table(ms, ack=False) as t:
        sel = t.getcol("FIELD_ID") == 0
        a1, a2 = t.getcol("ANTENNA1")[sel], t.getcol("ANTENNA2")[sel]
        data = t.getcol(column)[sel][..., [0, -1]]
    return np.array([np.degrees(np.angle(data[(a1 == p) & (a2 == q)].sum()))
                     for p, q in sorted(set(zip(a1.tolist(), a2.tolist())))])


@pytest.fixture(scope="module")
def non_closing_pair(tmp_path_factory):
    """86-GHz instrumental phases of PV and GL 300 deg apart: the reference phase of PV-GL
    starts a whole turn away from PV's minus GL's, so the count tracker's per-baseline
    count leaves 2 pi eps on that baseline that no antenna term can absorb."""
    import copy

    scene = copy.deepcopy(SCENE)
    scene["stations"][1]["bands"]["86"]["instrumental"]["phase_deg"] = 150
    scene["stations"][2]["bands"]["86"]["instrumental"]["phase_deg"] = -150
    return simulate(scene, tmp_path_factory.mktemp("non-closing"))


def test_non_closing_offsets_removed(non_closing_pair, tmp_path):
    ref, tgt = _copy(non_closing_pair, tmp_path)
    report = calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    assert np.abs(_target_phases(tgt)).max() < 1.0
    assert _target_coherence(tgt).min() >= COHERENCE
    residual = report["phase_referencing"]["methods"]["PWC_DATA"][0]["baseline_residual_deg"]
    # what the antenna model could not take: the first calibrator scan's per-baseline
    # integers, which need not close (19 deg on PV-GL with this scene)
    assert max(abs(v) for hands in residual.values() for v in hands.values()) > 10.0


def test_antenna_terms_alone_leave_closure_errors(non_closing_pair, tmp_path, monkeypatch):
    """The plausible antenna-only step: coherent target, but phases off on every baseline
    the per-baseline count touched (the image's closure phases)."""
    from hitops.calibrate.phaseref import apply as phase_ref

    monkeypatch.setattr(phase_ref, "baseline_factors",
                        lambda solution, ant1, ant2, corr_hands, n_ant: 1.0)
    ref, tgt = _copy(non_closing_pair, tmp_path)
    calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    assert np.abs(_target_phases(tgt)).max() > 10.0


def test_phase_without_delay_fails(pair, tmp_path):
    """A phase-only calibrator step (no per-channel delay) leaves the target decorrelated:
    the step's output with the solved delays taken back out is what it would write."""
    ref, tgt = _copy(pair, tmp_path)
    report = calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    window = report["phase_referencing"]["methods"]["PWC_DATA"][0]
    t_scan = np.array([s["time"] for s in window["scans"]])
    with pt.table(tgt, readonly=False, ack=False) as t:
        names = list(pt.table(f"{tgt}::ANTENNA", ack=False).getcol("NAME"))
        chan = pt.table(f"{tgt}::SPECTRAL_WINDOW", ack=False).getcol("CHAN_FREQ")[0]
        time, a1, a2 = t.getcol("TIME"), t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        delay = np.array([np.interp(time, t_scan, np.array(window["antennas"][n]["R"]["delay_ns"]))
                          for n in names]) * 1e-9
        dtau = delay[a1, np.arange(time.size)] - delay[a2, np.arange(time.size)]
        data = t.getcol("PWC_DATA")
        target = t.getcol("FIELD_ID") == 0
        undo = np.exp(2j * np.pi * (chan - chan.mean())[None, :] * dtau[:, None])
        data[target] *= undo[target][:, :, None]
        t.putcol("PWC_DATA", data)
    assert _target_coherence(tgt).min() < COHERENCE


def test_without_the_per_scan_integers_fails(pair, tmp_path, monkeypatch):
    """Solving and interpolating on scans whose integers are left in (every scan's count
    restarts: no integer found per scan) cannot work."""
    from hitops.testing.phaseref_scene import one_integer_per_baseline

    one_integer_per_baseline(monkeypatch)
    ref, tgt = _copy(pair, tmp_path)
    calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    assert _target_coherence(tgt).min() < COHERENCE


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "hitops.cli", "calibrate", *args],
                          capture_output=True, text=True, timeout=300)


def _columns(ms):
    with pt.table(ms, ack=False) as t:
        return sorted(t.colnames())


def _drop_field(ms: str, field_id: int) -> None:
    """The set without the rows of ``field_id`` (its FIELD row kept): a deep copy of the
    other rows (tiled columns do not allow removing rows)."""
    kept = ms + ".kept"
    with pt.table(ms, ack=False) as t:
        sel = t.selectrows(np.flatnonzero(t.getcol("FIELD_ID") != field_id))
        sel.copy(kept, deep=True, valuecopy=True)
        sel.close()
    shutil.rmtree(ms)
    shutil.move(kept, ms)


@pytest.mark.parametrize("case", ["unknown", "no-scans", "only-field", "n0-step"])
def test_bad_input_one_line_nothing_written(pair, tmp_path, case):
    ref, tgt = _copy(pair, tmp_path)
    args, expect = [ref, tgt, "--calibrator-field", "3C273"], "3C273"
    if case == "unknown":
        args[-1], expect = "J0000+0000", "no such field"
    elif case in ("no-scans", "only-field"):
        _drop_field(ref, 1)
        _drop_field(tgt, 1)
        if case == "only-field":
            args[-1], expect = "M87", "only field"
        else:
            expect = "no calibrator scans"
    else:
        args += ["--offset-model", "point"]
        expect = "--offset-model"
    before = _columns(tgt)
    result = _cli(*args)
    assert result.returncode == 2, result.stderr
    lines = [ln for ln in result.stderr.strip().splitlines() if "ERROR" in ln or "Error" in ln]
    assert len(lines) == 1 and expect in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert _columns(tgt) == before


@pytest.mark.parametrize("change, where", [
    (lambda s: s["observation"].pop("scan_length"), "observation.scan_length"),
    (lambda s: s["calibrator"].update(name="M87"), "calibrator.name"),
    (lambda s: s["calibrator"].pop("flux"), "calibrator.flux"),
    (lambda s: s["calibrator"].update(colour="red"), "calibrator.colour"),
])
def test_scene_calibrator_errors(change, where):
    import copy

    from hitops.errors import SceneError
    from hitops.simulate.scene import parse_scene

    scene = copy.deepcopy(SCENE)
    change(scene)
    with pytest.raises(SceneError, match=where.replace(".", r"\.")):
        parse_scene(scene)


def test_scene_calibrator_scans(pair):
    """Target and calibrator alternate as the scene says: 120 s, then 60 s, numbered in
    time order, each field's rows in its own scans."""
    with pt.table(str(pair["230"]), ack=False) as t:
        field, scan, time = t.getcol("FIELD_ID"), t.getcol("SCAN_NUMBER"), t.getcol("TIME")
        names = list(pt.table(f"{pair['230']}::FIELD", ack=False).getcol("NAME"))
    assert names == ["M87", "3C273"]
    for s in np.unique(scan):
        rows = scan == s
        assert np.unique(field[rows]).size == 1
        assert field[rows][0] == (0 if s % 2 else 1)
        span = time[rows].max() - time[rows].min() + 2.0
        assert span == pytest.approx(120.0 if s % 2 else 60.0)


def test_station_without_calibrator_solutions_is_flagged_on_the_target(pair, tmp_path):
    """A station whose calibrator rows are all flagged has no solution: its target rows
    end flagged in FLAG after the commit (and only they), the others stay coherent."""
    ref, tgt = _copy(pair, tmp_path)
    with pt.table(tgt, readonly=False, ack=False) as t:
        names = list(pt.table(f"{tgt}::ANTENNA", ack=False).getcol("NAME"))
        lost = len(names) - 1
        field, a1, a2 = t.getcol("FIELD_ID"), t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        touches = (a1 == lost) | (a2 == lost)
        flag = t.getcol("FLAG")
        flag[(field == 1) & touches] = True
        t.putcol("FLAG", flag)
        before = t.getcol("FLAG")
    report = calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    entry = report["phase_referencing"]["methods"]["PWC_DATA"][0]
    target_lost = (field == 0) & touches
    assert entry["target_rows_flagged"] == int(target_lost.sum()) > 0
    with pt.table(tgt, ack=False) as t:
        after = t.getcol("FLAG")
    assert after[target_lost].all()
    # nothing else lost its data: the other rows keep the flags the transfer gave them
    others = ~target_lost
    assert not (after[others] & ~before[others]).any()
    assert _target_coherence(tgt).min() >= COHERENCE


@pytest.fixture(scope="module")
def one_channel_pair(tmp_path_factory):
    """The scene with one 2-GHz channel at 230 GHz: no delay across the window to find
    each scan's integer from, so the count is carried across the switches (no slews)."""
    import copy

    scene = copy.deepcopy(SCENE)
    scene["bands"][1]["n_chan"] = 1
    # the carried count needs slews shorter than the reference band's coherence time
    # and one troposphere for both fields (docs/solutions.md): the packaged scene's
    # 60-s slews and own paths are what it cannot do, so they are taken out here
    scene["observation"]["scan_gap"] = 0
    scene["calibrator"].pop("own_troposphere")
    return simulate(scene, tmp_path_factory.mktemp("one-channel"))


def test_one_channel_window_carries_the_count(one_channel_pair, tmp_path):
    ref, tgt = _copy(one_channel_pair, tmp_path)
    report = calibrate_flat(ref, tgt, calibrator_field="3C273", ref_model_column="MODEL_DATA",
                   no_verdict=True)
    window = report["phase_referencing"]["methods"]["PWC_DATA"][0]
    assert window["integers"]["rule"] == "carried" and "switches" in window
    assert _target_coherence(tgt).min() >= COHERENCE


def test_one_channel_window_refuses_another_tracker(one_channel_pair, tmp_path):
    ref, tgt = _copy(one_channel_pair, tmp_path)
    before = _columns(tgt)
    result = _cli(ref, tgt, "--calibrator-field", "3C273", "--tracker", "antenna")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    lines = [ln for ln in result.stderr.strip().splitlines() if "ERROR" in ln]
    assert len(lines) == 1 and "one-channel target window" in lines[0], result.stderr[-2000:]
    assert _columns(tgt) == before
