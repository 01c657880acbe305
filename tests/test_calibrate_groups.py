"""Sets with two fields and two spectral windows per band are calibrated group by group.

Four synthetic pairs (fields A and B x a low and a high spectral window, each
with its own troposphere, source phases and R) are merged into one
reference-band and one target-band Measurement Set with python-casacore, the
second band's field and window numbers deliberately different from the
first's.  calibrate must pair the groups by field name and frequency order,
use each pair's own R, return the truth (CFPT = the source phase), and write
exactly what calibrating each pair on its own writes: rows of one group
never meet another's.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Troposphere
from hitops.errors import MeasurementSetError

from ms_columns import col  # tests/ is on sys.path (rootdir-relative)

#: (field, reference frequency, R) of the four pairs
GROUPS = [("A", 86e9, 228.0 / 86.0), ("A", 88e9, 232.0 / 88.0),
          ("B", 86e9, 228.0 / 86.0), ("B", 88e9, 232.0 / 88.0)]


def _append(base: str, other: str, field_id: int, ddid: int) -> None:
    """Append ``other``'s main-table rows to ``base`` with the given FIELD_ID / DATA_DESC_ID."""
    with pt.table(other, ack=False) as src, pt.table(base, readonly=False, ack=False) as dst:
        start, n = dst.nrows(), src.nrows()
        dst.addrows(n)
        for name in src.colnames():
            if name in ("FIELD_ID", "DATA_DESC_ID") or not src.iscelldefined(name, 0):
                continue
            dst.putcol(name, src.getcol(name), start, n)
        dst.putcol("FIELD_ID", np.full(n, field_id, np.int32), start, n)
        dst.putcol("DATA_DESC_ID", np.full(n, ddid, np.int32), start, n)


def _copy_row(base: str, other: str, subtable: str, **values) -> int:
    """Append row 0 of ``other``'s subtable to ``base``'s; returns its row number."""
    with pt.table(f"{other}::{subtable}", ack=False) as src, \
            pt.table(f"{base}::{subtable}", readonly=False, ack=False) as dst:
        row = dst.nrows()
        dst.addrows(1)
        for name in src.colnames():
            if src.iscelldefined(name, 0):
                dst.putcell(name, row, src.getcell(name, 0))
        for name, value in values.items():
            dst.putcell(name, row, value)
        return row


def _merge(parts, out: str, order) -> None:
    """One set from single-group sets: ``order`` lists (part, field name) in the order their
    field and window get numbers in this set (so the two bands can number them differently)."""
    first = parts[order[0]]
    shutil.copytree(first, out)
    with pt.table(f"{out}::FIELD", readonly=False, ack=False) as t:
        t.putcell("NAME", 0, GROUPS[order[0]][0])
    field_ids = {GROUPS[order[0]][0]: 0}
    spw_ids = {GROUPS[order[0]][1]: 0}
    with pt.table(out, readonly=False, ack=False) as t:
        t.putcol("FIELD_ID", np.zeros(t.nrows(), np.int32))
        t.putcol("DATA_DESC_ID", np.zeros(t.nrows(), np.int32))
    for k in order[1:]:
        name, freq, _ = GROUPS[k]
        if name not in field_ids:
            field_ids[name] = _copy_row(out, parts[k], "FIELD", NAME=name)
        if freq not in spw_ids:
            spw = _copy_row(out, parts[k], "SPECTRAL_WINDOW")
            spw_ids[freq] = _copy_row(out, parts[k], "DATA_DESCRIPTION", SPECTRAL_WINDOW_ID=spw,
                                      POLARIZATION_ID=0)
        _append(out, parts[k], field_ids[name], spw_ids[freq])


@pytest.fixture(scope="module")
def merged(tmp_path_factory, pair_store):
    root = tmp_path_factory.mktemp("groups")
    # the parts are only read (merged into new sets): the session's builds themselves
    truths = [pair_store.built(PairSpec(n_ant=4, n_time=120, ratio=ratio, ref_freq_hz=freq,
                                        n_scans=2, seed=40 + k,
                                        troposphere=Troposphere(phase_offset_rad=1.3)))
              for k, (_, freq, ratio) in enumerate(GROUPS)]
    ref, tgt = str(root / "ref.ms"), str(root / "target.ms")
    _merge([str(t.ref_ms) for t in truths], ref, [0, 1, 2, 3])
    # the target band numbers its fields and windows the other way round
    _merge([str(t.target_ms) for t in truths], tgt, [3, 2, 1, 0])
    return truths, ref, tgt, root


def test_each_group_gets_its_own_ratio_and_the_truth_back(merged, tmp_path):
    truths, ref, tgt, _ = merged
    work = str(tmp_path / "target.ms")
    shutil.copytree(tgt, work)
    report = calibrate_flat(ref, work, method="pwc,cfpt")
    groups = report["groups"]
    assert len(groups) == 4
    seen = {(g["field"], round(g["ref_freq_hz"])): g for g in groups}
    for name, freq, ratio in GROUPS:
        entry = seen[(name, round(freq))]
        assert entry["ratio"] == pytest.approx(ratio, rel=1e-12)
        assert entry["target_freq_hz"] == pytest.approx(freq * ratio, rel=1e-12)
        assert entry["rows"]["matched"] == entry["rows"]["target"] == 6 * 120
    # CFPT of each group: the source phase plus R times the reference phase's wraps
    # (2 pi R n), every row, through the group's own R
    with pt.table(work, ack=False) as t:
        field_id, ddid = t.getcol("FIELD_ID"), t.getcol("DATA_DESC_ID")
    cfpt = col(work, "CFPT_DATA")[:, 0, :]
    names = {0: "B", 1: "A"}                    # the target's numbering (see merged)
    freqs = {0: 88e9, 1: 86e9}
    for k, (name, freq, ratio) in enumerate(GROUPS):
        fid = [f for f, n in names.items() if n == name][0]
        dd = [d for d, f in freqs.items() if f == freq][0]
        rows = (field_id == fid) & (ddid == dd)
        truth = truths[k]
        assert rows.sum() == truth.source_phase.shape[0]
        wraps = truth.ref_phase_true - np.angle(np.exp(1j * truth.ref_phase_true))
        expected = truth.source_phase + ratio * wraps
        residual = np.angle(cfpt[rows] * np.exp(-1j * expected))
        assert np.max(np.abs(residual)) < 1e-5, (name, freq)


def test_groups_never_mix(merged, tmp_path):
    """Each group's output rows equal calibrating that group's own pair alone."""
    truths, ref, tgt, _ = merged
    work = str(tmp_path / "target.ms")
    shutil.copytree(tgt, work)
    calibrate_flat(ref, work, method="pwc,cfpt,cwu", offset_model="point")
    with pt.table(work, ack=False) as t:
        field_id, ddid = t.getcol("FIELD_ID"), t.getcol("DATA_DESC_ID")
    names, freqs = {"B": 0, "A": 1}, {88e9: 0, 86e9: 1}
    for k, (name, freq, _) in enumerate(GROUPS):
        alone = str(tmp_path / f"alone{k}.ms")
        shutil.copytree(truths[k].target_ms, alone)
        calibrate_flat(str(truths[k].ref_ms), alone, method="pwc,cfpt,cwu", offset_model="point")
        rows = (field_id == names[name]) & (ddid == freqs[freq])
        for column in ("PWC_DATA", "CFPT_DATA", "CWU_DATA", "FLAG"):
            np.testing.assert_array_equal(col(work, column)[rows], col(alone, column),
                                          err_msg=f"{name} {freq} {column}")


@pytest.fixture(scope="module")
def two_fields(tmp_path_factory):
    """A target and a calibrator in alternating scans (the packaged phaseref scene, 20
    minutes, no noise): two groups with different numbers of rows."""
    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    scene = load_scene_mapping("phaseref")[0]
    scene["observation"]["duration"] = 1200
    scene["corruptions"]["noise"] = False
    return simulate(scene, tmp_path_factory.mktemp("two-fields"))


@pytest.mark.parametrize("tracker", ["count", "antenna"])
def test_several_groups_cut_into_chunks_write_what_one_chunk_writes(two_fields, tmp_path,
                                                                    tracker):
    """Chunks are one group's time chunks: every group of a set with several fields opened
    with its own (dask-ms applied one group's chunks to every group and refused a group of
    another length: "Chunks do not add up to shape")."""
    ref = two_fields["86"]
    whole, chunked = str(tmp_path / "whole.ms"), str(tmp_path / "chunked.ms")
    shutil.copytree(two_fields["230"], whole)
    shutil.copytree(two_fields["230"], chunked)
    with pt.table(whole, ack=False) as t:
        sizes = np.bincount(t.getcol("FIELD_ID"))
    assert sizes.size == 2 and sizes[0] != sizes[1]
    calibrate_flat(ref, whole, method="pwc,cfpt", tracker=tracker, no_verdict=True)
    report = calibrate_flat(ref, chunked, method="pwc,cfpt", tracker=tracker, chunk_rows=500,
                       no_verdict=True)
    assert all(g["chunks"] > 1 for g in report["groups"]), report["groups"]
    for column in ("PWC_DATA", "CFPT_DATA", "FLAG"):
        np.testing.assert_array_equal(col(chunked, column), col(whole, column), err_msg=column)


def test_window_counts_that_cannot_pair_are_refused(merged, tmp_path):
    """Two reference windows against one target window: refused, naming both sets' windows."""
    truths, ref, _, root = merged
    tgt = str(tmp_path / "one-window.ms")
    _merge([str(t.target_ms) for t in truths], tgt, [0, 2])     # fields A, B; low window only
    before = json.dumps(sorted(pt.table(tgt, ack=False).colnames()))
    with pytest.raises(MeasurementSetError, match=r"field A: 2 spectral windows in .*ref.ms"
                                                  r".*and 1 in .*one-window.ms"):
        calibrate_flat(ref, tgt, method="pwc")
    assert json.dumps(sorted(pt.table(tgt, ack=False).colnames())) == before


def test_one_group_of_a_set_with_two_field_rows_in_several_chunks(tmp_path, new_pair):
    """A set whose FIELD table has two rows but whose rows all use the second (a split
    that kept the FIELD table) is one group; cut into chunks and sorted by TIME it is
    reopened under the same group key (the reopen once dropped the grouping and asked
    for field 0) and gives what the plain set gives."""
    truth = new_pair(PairSpec(n_ant=4, n_time=600, seed=3), tmp_path / "plain")
    ref, tgt = str(tmp_path / "ref.ms"), str(tmp_path / "tgt.ms")
    shutil.copytree(truth.ref_ms, ref)
    shutil.copytree(truth.target_ms, tgt)
    for ms in (ref, tgt):
        _copy_row(ms, ms, "FIELD", NAME="M87")
        with pt.table(ms, readonly=False, ack=False) as t:
            t.putcol("FIELD_ID", np.ones(t.nrows(), np.int32))
    plain = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", chunk_rows=1000)
    moved = calibrate_flat(ref, tgt, method="pwc", chunk_rows=1000)
    assert plain["chunks"] == moved["chunks"] > 2
    np.testing.assert_array_equal(col(tgt, "PWC_DATA"), col(truth.target_ms, "PWC_DATA"))


def test_export_of_a_set_with_a_field_left_out_is_refused_before_anything_is_written(
        merged, tmp_path):
    """The target set holds fields A and B, the reference band A only: the run would
    calibrate A and leave B out, but --export-uvfits writes the whole target set, and a
    UVFITS file holds one field.  Refused before the commit (it used to fail after the
    columns were written), naming both fields and the one calibrated."""
    from hitops.errors import InputError

    truths, _, _, _ = merged
    ref, tgt = str(tmp_path / "ref-A.ms"), str(tmp_path / "target-AB.ms")
    _merge([str(t.ref_ms) for t in truths], ref, [0])            # field A, low window
    _merge([str(t.target_ms) for t in truths], tgt, [0, 2])      # fields A and B, low window
    before = sorted(pt.table(tgt, ack=False).colnames())
    out = tmp_path / "never.uvfits"
    with pytest.raises(InputError, match=r"--export-uvfits .*never\.uvfits: .*target-AB\.ms "
                                         r"holds 2 fields \(A, B\), of which the run calibrates "
                                         r"A only, and a UVFITS file holds one field"):
        calibrate_flat(ref, tgt, method="pwc", export_uvfits=str(out), no_verdict=True)
    assert sorted(pt.table(tgt, ack=False).colnames()) == before and not out.exists()
    # without the export the same pair runs: field B is left out, A calibrated
    calibrate_flat(ref, tgt, method="pwc", no_verdict=True)
    report = json.loads((tmp_path / "target-AB.ms.hitops-calibrate.json").read_text())
    with pt.table(tgt, ack=False) as t:
        n_field_a = int(np.sum(t.getcol("FIELD_ID") == 0))
        assert "PWC_DATA" in t.colnames() and 0 < n_field_a < t.nrows()
    assert report["rows"]["matched"] == n_field_a
