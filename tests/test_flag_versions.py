"""CASA flag versions written and read by hitops, and the flags a rerun starts from.

The truth comes from CASA itself: flagmanager lists and restores the versions hitops
writes, and hitops restores the ones flagmanager writes, so a recipe's kept versions
are ones a CASA user can list and restore.  Then: ``hitops calibrate --restore-flags``
on a set whose FLAG an earlier step changed gives what a fresh set gives, which the
same run without it does not (the bug of issue 35).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from casacore import tables as pt

from hitops.casa.runner import run_task
from hitops.errors import InputError
from hitops.io import flag_versions as fv


def _flags(ms):
    with pt.table(str(ms), ack=False) as t:
        return t.getcol("FLAG"), t.getcol("FLAG_ROW")


def _set_flags(ms, flag):
    with pt.table(str(ms), readonly=False, ack=False) as t:
        t.putcol("FLAG", flag)


def _listed(ms):
    listing = run_task("flagmanager", vis=str(ms), mode="list")
    return {v["name"]: v["comment"] for k, v in listing.items() if k != "MS"}


def test_casa_lists_and_restores_hitops_versions_and_hitops_restores_casas(new_demo):
    _, target = new_demo
    # the simulator kept the flags as simulated
    assert _listed(target) == {"hitops_original": "flags as simulated (hitops)"}
    original, original_row = _flags(target)
    assert not original.any()
    run_task("flagdata", vis=str(target), mode="manual", antenna="AP", flagbackup=False)
    ap_flags, _ = _flags(target)
    assert 0 < ap_flags.mean() < 1
    fv.save_version(target, "ap", "AP flagged by hand")
    # CASA restores hitops's versions ...
    run_task("flagmanager", vis=str(target), mode="restore", versionname="hitops_original")
    assert np.array_equal(_flags(target)[0], original)
    run_task("flagmanager", vis=str(target), mode="restore", versionname="ap")
    assert np.array_equal(_flags(target)[0], ap_flags)
    # ... and hitops restores CASA's, alone or as a union
    fv.restore_versions(target, ["hitops_original"])
    run_task("flagdata", vis=str(target), mode="manual", antenna="PV", flagbackup=False)
    pv_flags, _ = _flags(target)
    run_task("flagmanager", vis=str(target), mode="save", versionname="pv", comment="PV")
    fv.restore_versions(target, ["hitops_original"])
    fv.restore_versions(target, ["pv"])
    assert np.array_equal(_flags(target)[0], pv_flags)
    fv.restore_versions(target, ["ap", "pv"])
    assert np.array_equal(_flags(target)[0], ap_flags | pv_flags)
    # saving a version again replaces it where it stood in CASA's list
    fv.save_version(target, "ap", "AP and PV")
    assert list(_listed(target).items()) == [
        ("hitops_original", "flags as simulated (hitops)"), ("ap", "AP and PV"), ("pv", "PV")]


def test_a_missing_or_foreign_version_is_refused_with_flag_as_it_was(new_demo, tmp_path):
    ref, target = new_demo
    before = _flags(target)[0].copy()
    before[::3] = True
    _set_flags(target, before)
    with pytest.raises(InputError, match=r"no flag version 'ffsc' .* \(versions: hitops_original\)"):
        fv.restore_versions(target, ["hitops_original", "ffsc"])
    assert np.array_equal(_flags(target)[0], before)
    # a version of another set (a shorter track: other rows) is not restored
    from hitops.simulate import simulate
    simulate("demo", tmp_path / "other", duration=120)
    shutil.copytree(fv.versions_dir(tmp_path / "other" / "sim-230.ms") / "flags.hitops_original",
                    fv.versions_dir(target) / "flags.other")
    with pytest.raises(InputError, match="has 600 rows but .* has 3000: the version belongs to an "
                       "earlier set"):
        fv.restore_versions(target, ["other"])
    assert np.array_equal(_flags(target)[0], before)


def test_calibrate_from_the_kept_flags_equals_a_fresh_run(new_demo, tmp_path):
    from hitops.calibrate import calibrate_flat

    ref, target = new_demo
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    fresh_target = fresh / "sim-230.ms"
    shutil.copytree(target, fresh_target)
    shutil.copytree(fv.versions_dir(target), fv.versions_dir(fresh_target))
    calibrate_flat(str(ref), str(fresh_target), method="pwc", no_verdict=True,
              report=str(fresh / "r.json"))
    expected_flag, _ = _flags(fresh_target)
    with pt.table(str(fresh_target), ack=False) as t:
        expected_pwc = t.getcol("PWC_DATA")
    # an earlier step flagged a third of the target (as CASA applycal's calflag does)
    stale = np.zeros_like(expected_flag)
    stale[::3] = True
    _set_flags(target, stale)
    calibrate_flat(str(ref), str(target), method="pwc", no_verdict=True, report=str(tmp_path / "a.json"),
              restore_flags="hitops_original", save_flags="pwc")
    flag, _ = _flags(target)
    assert np.array_equal(flag, expected_flag)
    with pt.table(str(target), ack=False) as t:
        assert np.array_equal(t.getcol("PWC_DATA"), expected_pwc)
    assert np.array_equal(fv.read_version(target, ["pwc"])[0], flag)
    comment = dict((v.name, v.comment) for v in fv.list_versions(target))["pwc"]
    assert "hitops calibrate --method pwc -> PWC_DATA" in comment
    # the same run without --restore-flags keeps the stale flags (what reruns did before)
    _set_flags(target, stale)
    calibrate_flat(str(ref), str(target), method="pwc", no_verdict=True, overwrite=True,
              report=str(tmp_path / "b.json"))
    assert not np.array_equal(_flags(target)[0], expected_flag)
