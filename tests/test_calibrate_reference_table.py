"""``hitops calibrate --reference-table``: real CASA solutions in, the target column and table out.

The pair is laid out by casatools.simulator (tests/solutions_scene.py: PV, PB, AP, GL; 20
min of 1-s integrations; one 16 x 125 MHz window at 86 GHz; two 16 x 125 MHz target
windows at 227.1 and 229.1 GHz; a point source seen through per-antenna excess paths, no
noise).  The truth is physics: the target's DATA carry exp(i 2*pi*nu_k*(L_p - L_q)/c), so
a right transfer leaves every channel of every window and baseline coherent over the whole
track.  Real CASA fringefit/gaincal solve the reference band; ``hitops calibrate`` runs as
the user runs it (a subprocess of the installed command); real CASA applycal applies the
table it writes.  The plausible wrong transfer (the solution phases scaled without
counting their wraps: ``--method cfpt``, hitops.solutions' ``wrap_counting=False``)
fails the same check.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.casa.runner import run_task
from hitops.casa.tasks import gaincal
from solutions_scene import refant_sets_halfway
from test_io_metadata import counted_opens  # noqa: F401 - the fixture, shared

pytestmark = pytest.mark.slow

HITOPS = Path(sys.executable).with_name("hitops")
COHERENCE_MIN = 0.99


@pytest.fixture(scope="module")
def solved(fringe_fitted):
    """The pair and CASA fringefit's 4-s solutions of its reference band (the session's,
    read-only: each test writes a copy of the target)."""
    return fringe_fitted


def hitops(*args):
    proc = subprocess.run([str(HITOPS), "calibrate", *map(str, args)], capture_output=True,
                          text=True, timeout=600)
    return proc.returncode, proc.stdout + proc.stderr


def _target(pair, tmp_path, name="target.ms"):
    target = tmp_path / name
    shutil.copytree(pair.target_ms, target)
    return target


def _coherence(ms, column, rows=None):
    """Whole-track coherence per (field, window, baseline): (n_chan, n_corr) arrays."""
    with pt.table(str(ms), ack=False) as t:
        data, flag = t.getcol(column), t.getcol("FLAG")
        key = (t.getcol("FIELD_ID") * 100000 + t.getcol("DATA_DESC_ID") * 10000
               + t.getcol("ANTENNA1") * 100 + t.getcol("ANTENNA2"))
    if rows is not None:
        data, flag, key = data[rows], flag[rows], key[rows]
    out = {}
    for k in np.unique(key):
        sel = key == k
        phasor = np.where(flag[sel], 0.0, np.exp(1j * np.angle(data[sel])))
        out[int(k)] = np.abs(phasor.sum(axis=0)) / np.maximum((~flag[sel]).sum(axis=0), 1)
    return out


def _worst(coherence):
    return min(float(c.min()) for c in coherence.values())


def _applycal_difference(ms, table, column):
    """|phase(applycal of ``table``) - phase(``column``)| on the samples both leave unflagged."""
    with pt.table(str(ms), ack=False) as t:
        flag_before = t.getcol("FLAG")
    run_task("applycal", vis=str(ms), gaintable=[str(table)], interp=["linear"],
             applymode="calflag", calwt=[False], flagbackup=False)
    with pt.table(str(ms), ack=False) as t:
        corrected, ours, flag = t.getcol("CORRECTED_DATA"), t.getcol(column), t.getcol("FLAG")
    both = ~flag & ~flag_before
    return np.abs(np.angle(corrected * np.conj(ours)))[both], both


def test_fringefit_table_to_target_column_and_table(solved, tmp_path):
    pair, table = solved
    target = _target(pair, tmp_path)
    caltable = tmp_path / "target.fringe"
    report_path = tmp_path / "report.json"
    rc, out = hitops(pair.ref_ms, target, "--reference-table", table, "--method", "pwc,cfpt",
                     "--caltable", caltable, "--report", report_path)
    assert rc == 0, out
    coherence = _coherence(target, "PWC_DATA")
    assert len(coherence) == 2 * 6                 # two windows x six baselines
    assert all(c.shape == (16, 2) for c in coherence.values())
    assert _worst(coherence) >= COHERENCE_MIN       # every channel of every window
    # the same solutions scaled without counting their wraps (R_k * phi) fail it
    assert _worst(_coherence(target, "CFPT_DATA")) < 0.5
    report = json.loads(report_path.read_text())
    pwc = report["reference_table"]["methods"]["pwc"]
    assert report["reference_table"]["kind"] == "Fringe Jones"
    assert pwc["wrap_counting"] and not report["reference_table"]["methods"]["cfpt"]["wrap_counting"]
    assert pwc["reference_freq_hz"] == pytest.approx([86.0e9])
    assert pwc["refant_changes"] == [] and pwc["common_refant"] == ["PV"]
    wraps = {a["name"]: a["n_wraps"] for a in pwc["antennas"]}
    assert wraps["PV"] == 0 and min(wraps[s] for s in ("PB", "AP", "GL")) > 10
    assert report["samples"]["not_calibrated"] == 0
    assert report["caltable"]["rows"] == 300 * 4 * 2
    # the tracking section is what the run tracked: each antenna's counted wraps, which
    # hitops diagnose reads beside the coherence
    tracking = report["tracking"]
    assert tracking["setup"] == {"tracker": "reference-table", "segments": pwc["n_segments"],
                                 "wrap_counting": True}
    assert {a["antenna"]: a["wraps"] for a in tracking["antennas"]} == wraps
    assert {a["antenna"]: a["solutions"] for a in tracking["antennas"]} == \
        {a["name"]: a["n_solutions"] for a in pwc["antennas"]}
    # diagnose's reader of the report (hitops diagnose itself refuses this scene's two
    # polarization setups, one per window)
    from hitops.diagnose.confidence import cell, load

    info, warnings = load(str(target), str(report_path))
    assert warnings == [] and info["tracker"] == "reference-table"
    assert {a: e["wraps"] for a, e in info["antennas"].items()} == wraps
    assert cell(info["antennas"]["PB"]) == f"{wraps['PB']} wraps"
    # CASA applycal of the written table equals the column (it follows the rates between
    # the 4-s solutions, and so does the column)
    diff, both = _applycal_difference(target, caltable, "PWC_DATA")
    assert both.mean() > 0.99
    assert (diff < 0.01).mean() >= 0.99
    with pt.table(str(target), ack=False) as t:
        assert not [c for c in t.colnames() if c.startswith("HITOPS_PARTIAL_")]


def test_solutions_at_every_integration_match_applycal_to_1e6(solved, tmp_path):
    """gaincal G Jones at solint 'int': the table's solutions are the column's samples."""
    pair, _ = solved
    table = tmp_path / "ref.G"
    gaincal(str(pair.ref_ms), str(table), solint="int", refant="PV,PB", calmode="p",
            minsnr=3.0, minblperant=2)
    target = _target(pair, tmp_path)
    caltable = tmp_path / "target.fringe"
    rc, out = hitops(pair.ref_ms, target, "--reference-table", table, "--caltable", caltable)
    assert rc == 0, out
    assert _worst(_coherence(target, "PWC_DATA")) >= COHERENCE_MIN
    diff, _ = _applycal_difference(target, caltable, "PWC_DATA")
    assert (diff < 1e-6).mean() >= 0.99


def test_reference_antenna_change_reported(solved, tmp_path):
    """PV flagged for the second half: fringefit refers to PB from then on."""
    pair, _ = solved
    ref_ms, table = refant_sets_halfway(pair, tmp_path)
    target = _target(pair, tmp_path)
    rc, out = hitops(ref_ms, target, "--reference-table", table)
    assert rc == 0, out
    assert "reference antenna PV -> PB" in out
    report = json.loads(Path(f"{target}.hitops-calibrate.json").read_text())
    (change,) = report["reference_table"]["methods"]["pwc"]["refant_changes"]
    assert (change["from_antenna"], change["to_antenna"], change["bridged"]) == ("PV", "PB", True)
    # PV's baselines lose their second half (no PV solution there): flagged, reported
    assert report["samples"]["not_calibrated"] > 0
    assert _worst(_coherence(target, "PWC_DATA")) >= COHERENCE_MIN


def _scan_coherence(ms, column, starts):
    """Coherence per (scan, window, baseline): {key: (n_chan, n_corr)}."""
    with pt.table(str(ms), ack=False) as t:
        time = t.getcol("TIME")
        scan = np.searchsorted(np.asarray(starts), time - time.min(), side="right")
    out = {}
    for s in np.unique(scan):
        for k, c in _coherence(ms, column, scan == s).items():
            out[(int(s), k)] = c
    return out


def test_n0_step_per_antenna_and_scan(tmp_path):
    """Two fields in alternating 100-s scans: each antenna's count restarts at every scan,
    so the track is coherent per scan but not across scans until the integers per antenna
    and scan are solved against a point source (--offset-model point)."""
    from solutions_scene import make_solution_pair
    from hitops.casa.tasks import fringefit

    starts = [110.0 * k for k in range(6)]
    scans = [("M87" if k % 2 == 0 else "3C273", t0, t0 + 100.0) for k, t0 in enumerate(starts)]
    pair = make_solution_pair(tmp_path, seed=5, scans=scans)
    table = tmp_path / "ref.fringe"
    fringefit(str(pair.ref_ms), str(table), solint="4s", refant="PV,PB", minsnr=3.0)
    target = pair.target_ms
    rc, out = hitops(pair.ref_ms, target, "--reference-table", table, "--output-column", "PWC_NO_N0")
    assert rc == 0, out
    assert _worst(_scan_coherence(target, "PWC_NO_N0", starts)) >= COHERENCE_MIN
    assert _worst(_coherence(target, "PWC_NO_N0")) < 0.9          # across scans
    caltable = tmp_path / "target.fringe"
    rc, out = hitops(pair.ref_ms, target, "--reference-table", table, "--offset-model", "point",
                     "--caltable", caltable)
    assert rc == 0, out
    assert _worst(_coherence(target, "PWC_DATA")) >= COHERENCE_MIN   # whole track, per field
    report = json.loads(Path(f"{target}.hitops-calibrate.json").read_text())
    solves = report["offsets"]["solves"]
    assert {(s["field"], s["receptor"]) for s in solves} == {(0, 0), (0, 1), (1, 0), (1, 1)}
    assert any(k for s in solves for k in s["k"].values())
    # the table carries the integers too: applycal of it equals the column
    diff, _ = _applycal_difference(target, caltable, "PWC_DATA")
    assert (diff < 0.01).mean() >= 0.99


# ---- bad input: one line, non-zero exit, nothing written -------------------------------------

def _snapshot(*paths):
    out = {}
    for root in map(Path, paths):
        files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
        for path in sorted(files):
            if path.name != "table.lock":
                out[str(path)] = hashlib.sha1(path.read_bytes()).hexdigest()
    return out


def _refused(args, culprit, target, inputs, tmp_path):
    report = Path(f"{target}.hitops-calibrate.json")
    existed = report.exists()
    before = _snapshot(target, report, *inputs)
    caltable = tmp_path / "never.fringe"
    rc, out = hitops(*args, "--caltable", caltable)
    assert rc != 0, out
    assert "Traceback" not in out, out
    errors = [line for line in out.splitlines() if " ERROR " in line]
    assert len(errors) == 1 and culprit in errors[0], out
    assert _snapshot(target, report, *inputs) == before
    assert not caltable.exists() and report.exists() == existed


def test_refused_tables(solved, tmp_path):
    from hitops.io.caltable import _create_empty

    pair, table = solved
    target = _target(pair, tmp_path)
    bandpass = tmp_path / "empty.B"
    _create_empty(str(pair.ref_ms), str(bandpass), "Complex", "B Jones")
    _refused([pair.ref_ms, target, "--reference-table", bandpass],
             "'B Jones' table; supported: Fringe Jones, G Jones, T Jones", target, [bandpass], tmp_path)
    # solved on another set: a copy of REF_MS whose fourth station is named differently
    renamed = tmp_path / "renamed.ms"
    shutil.copytree(pair.ref_ms, renamed)
    with pt.table(f"{renamed}::ANTENNA", readonly=False, ack=False) as t:
        t.putcol("NAME", [*t.getcol("NAME")[:3], "KP"])
    _refused([renamed, target, "--reference-table", table], "was solved on another set",
             target, [table, renamed], tmp_path)
    # a station without one unflagged solution
    flagged = tmp_path / "gl_flagged.fringe"
    shutil.copytree(table, flagged)
    run_task("flagdata", vis=str(flagged), mode="manual", antenna="GL", flagbackup=False)
    _refused([pair.ref_ms, target, "--reference-table", flagged],
             "no unflagged solution for station(s) GL", target, [flagged], tmp_path)
    # 60-s phase solutions: the phase moves by more than pi between them
    slow = tmp_path / "ref60.G"
    gaincal(str(pair.ref_ms), str(slow), solint="60s", refant="PV,PB", calmode="p", minsnr=3.0,
            minblperant=2)
    _refused([pair.ref_ms, target, "--reference-table", slow],
             "moves by more than pi between solutions 60 s apart", target, [slow], tmp_path)
    # a damaged table: one of its files lost (casacore alone says "FiledesIO ...")
    damaged = tmp_path / "damaged.fringe"
    shutil.copytree(table, damaged)
    (damaged / "table.f0").unlink()
    _refused([pair.ref_ms, target, "--reference-table", damaged],
             f"'{damaged}' is damaged", target, [damaged], tmp_path)


@pytest.mark.parametrize("extra, culprit", [
    (["--method", "cwu"], "--method cwu with --reference-table"),
    (["--method", "pwc", "--offset-model", "point", "--offset-reference-column", "DATA"],
     "both set the n0 offset step"),
    (["--tracker", "antenna"], "--tracker antenna with --reference-table"),
    (["--method", "cfpt", "--offset-model", "point"], "add pwc to --method"),
    (["--ratio", "2.6"], "--ratio with --reference-table"),
    (["--calibrator-field", "CAL"], "--calibrator-field CAL with --reference-table"),
])
def test_refused_combinations(solved, tmp_path, extra, culprit):
    pair, table = solved
    target = _target(pair, tmp_path)
    _refused([pair.ref_ms, target, "--reference-table", table, *extra], culprit, target, [table],
             tmp_path)


def test_existing_output_needs_overwrite(solved, tmp_path):
    pair, table = solved
    target = _target(pair, tmp_path)
    assert hitops(pair.ref_ms, target, "--reference-table", table)[0] == 0
    with pt.table(str(target), ack=False) as t:
        first = t.getcol("PWC_DATA")
    _refused([pair.ref_ms, target, "--reference-table", table], "already exists", target,
             [table], tmp_path)
    rc, out = hitops(pair.ref_ms, target, "--reference-table", table, "--overwrite")
    assert rc == 0, out
    with pt.table(str(target), ack=False) as t:
        np.testing.assert_array_equal(t.getcol("PWC_DATA"), first)


def test_channel_lattice_resolves_what_the_centre_lattice_cannot():
    """Edge sums of four antennas over three segments on a 16-channel window at 227.1 GHz
    from 86 GHz, each edge off by a few degrees (what the solution interval leaves of the
    troposphere): per channel the integers come out exact; the centre phase alone (the
    one-channel lattice on the channel sums) takes a neighbour whose centre phase is within
    those degrees but whose slope across the window is wrong (39 turns: 4 deg at the centre,
    5.7 rad across the window)."""
    from hitops.calibrate.n0.channel_lattice import solve_channels
    from hitops.calibrate.n0.lattice import solve_lattice

    freq = 227.1e9 + (np.arange(16) - 7.5) * 125e6
    ratios = freq / 86.0e9
    rng = np.random.default_rng(4)
    truth = np.zeros((4, 3), np.int64)
    truth[1:] = rng.integers(-20, 21, size=(3, 3))
    truth[2, 1] = 45                               # 45 - 39 = 6 is 4 deg away at the centre
    node = {(p, s): 3 * p + s for p in range(4) for s in range(3)}
    a, b, z, n = [], [], [], []
    for s in range(3):
        for p in range(4):
            for q in range(p + 1, 4):
                # Phi_model - Phi_out: the output carries 2*pi*R_k*(truth_q - truth_p)
                a.append(node[(p, s)])
                b.append(node[(q, s)])
                error = np.radians(rng.normal(0.0, 5.0))
                z.append(50 * np.exp(1j * (2 * np.pi * ratios * (truth[p, s] - truth[q, s]) + error)))
                n.append(np.full(16, 50))
    gauge = [node[(0, s)] for s in range(3)]
    sol = solve_channels(12, a, b, np.array(z), np.array(n), ratios, 50, gauge)
    np.testing.assert_array_equal(sol.k, truth.ravel())
    assert sol.score > 0.99 * float(np.sum(n))
    centre = solve_lattice(12, a, b, np.array(z).sum(axis=1), np.array(n).sum(axis=1),
                           ratios.mean() % 1.0, 50, gauge_order=gauge)
    assert not np.array_equal(centre.k, truth.ravel())


def test_memory_budget_cuts_the_table_path_into_chunks(solved, tmp_path):
    """--memory-budget sets the rows per chunk (hitops/calibrate/memory.py's model, as the
    visibility path): a budget of about 2500 rows gives several chunks, each read while the
    one before is corrected, and the same column and flags as one chunk."""
    from hitops.calibrate import memory

    pair, table = solved
    whole, chunked = _target(pair, tmp_path, "whole.ms"), _target(pair, tmp_path, "chunked.ms")
    with pt.table(str(whole), ack=False) as t:
        n_rows, (n_chan, n_corr) = t.nrows(), t.getcell("DATA", 0).shape
    per_row = memory.bytes_per_row(n_corr, n_chan, 1) + memory.read_bytes_per_row(n_corr, n_chan)
    budget = (memory.FIXED_BYTES + memory.LOCAL_ORDER_BYTES_PER_ROW * n_rows + 2500 * per_row)
    rows = memory.rows_for_budget(budget, n_rows, n_corr, n_chan, 1, local=True)
    assert 1000 <= rows < n_rows / 3
    rc, out = hitops(pair.ref_ms, chunked, "--reference-table", table, "--memory-budget", budget)
    assert rc == 0, out
    assert f"up to {rows} target rows per chunk" in out
    assert hitops(pair.ref_ms, whole, "--reference-table", table, "--chunk-rows", n_rows)[0] == 0
    with pt.table(str(whole), ack=False) as a, pt.table(str(chunked), ack=False) as b:
        for column in ("PWC_DATA", "FLAG"):
            np.testing.assert_array_equal(a.getcol(column), b.getcol(column))


def test_each_subtable_of_both_sets_is_read_once(solved, tmp_path, counted_opens):
    """The table path reads each set's subtables once for the whole run (its SetMetadata,
    passed down to the transfer of every method), counted on python-casacore's own opens."""
    from hitops.calibrate import calibrate_flat

    pair, table = solved
    target = _target(pair, tmp_path)
    counted_opens.clear()
    calibrate_flat(str(pair.ref_ms), str(target), method="pwc,cfpt", reference_table=str(table),
              chunk_rows=5000)
    for ms in (str(pair.ref_ms), str(target)):
        subtables = {name: n for name, n in counted_opens.items() if name.startswith(ms + "::")}
        assert set(subtables) == {f"{ms}::{s}" for s in ("ANTENNA", "FIELD", "SPECTRAL_WINDOW",
                                                           "DATA_DESCRIPTION", "POLARIZATION")}
        assert set(subtables.values()) == {1}, subtables
