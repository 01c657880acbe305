"""``--calibrator-field`` on MSv4 processing sets equals the step on the v2 sets they came from.

Truth: the same run on the Measurement Sets v2 that xradio converted, whose step is checked
against the physics in tests/test_sfpr.py and tests/test_phase_referencing.py.  The pair is
the one casatools.simulator lays out for issue 38 (hitops/testing/phaseref_scene.py: 60-s
slews, a resolved calibrator with its model in MODEL_DATA of both bands, 16 channels, so
each scan's integer comes from its delay), cut to 15 minutes, 3% of both bands' samples
flagged.  Converted twice: as xradio does by default (one partition holding both fields)
and one partition per field (as ``hitops simulate --format msv4`` writes, so the step's
rows span two partitions).  The one-channel scene of tests/test_phase_referencing.py
(the count carried across the switches, read from the reference band) checks the other
rule.  Each method's data group must hold the v2 run's column and FLAG (to float32
rounding), the report's phase referencing entry must be the v2 run's, and the input
arrays stay byte for byte as they were.  Cost: about 30 s here.
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.errors import HitopsError  # noqa: E402
from hitops.testing.phaseref_scene import PhaserefSpec, make_phaseref_pair  # noqa: E402
from msv4_sets import copies_of, file_digests  # noqa: E402
from test_msv4_calibrate import (_flag_some, _input_digests,  # noqa: E402
                                 assert_group_equals_column)

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")

#: methods whose integers the 15-minute scene decides (cfpt's are too close on one scan)
METHODS = ("pwc", "cwu")


def _convert(ms, out: Path, by_field: bool) -> str:
    from xradio.measurement_set import convert_msv2_to_processing_set

    logging.getLogger("toolviper").setLevel(logging.WARNING)
    convert_msv2_to_processing_set(str(ms), str(out),
                                   partition_scheme=["FIELD_ID"] if by_field else [])
    return str(out)


@pytest.fixture(scope="module")
def sfpr(tmp_path_factory):
    """{v2 ref, v2 target, and the v4 stores of both partition schemes}."""
    root = tmp_path_factory.mktemp("v4sfpr")
    pair = make_phaseref_pair(root, PhaserefSpec(duration_s=900.0))
    _flag_some(pair.ref_ms, pair.target_ms)
    out = {"ref2": str(pair.ref_ms), "tgt2": str(pair.target_ms)}
    for scheme, by_field in (("one", False), ("fields", True)):
        for band, ms in (("ref", pair.ref_ms), ("tgt", pair.target_ms)):
            out[f"{band}4-{scheme}"] = _convert(ms, root / f"{band}-{scheme}.ps.zarr", by_field)
    return out



def _step_entry(report) -> dict:
    """The report's phase referencing entry, as the JSON file holds it."""
    return json.loads(json.dumps(report["phase_referencing"]))


def _run_both(ref2, tgt2, ref, tgt4, **options):
    flags = dict(method=",".join(METHODS), no_verdict=True, calibrator_field="CAL",
                 ref_model_column="MODEL_DATA", chunk_rows=200, **options)
    r2 = calibrate_flat(ref2, tgt2, **flags)
    r4 = calibrate_flat(ref, tgt4, **flags)
    return r2, r4


@pytest.mark.parametrize("scheme, reference", [("one", "v4"), ("fields", "v4"),
                                               ("fields", "v2")])
def test_calibrator_step_on_v4_writes_what_the_v2_step_writes(sfpr, tmp_path, scheme,
                                                              reference):
    ref2, tgt2, ref4, tgt4 = copies_of([sfpr["ref2"], sfpr["tgt2"], sfpr[f"ref4-{scheme}"],
                                      sfpr[f"tgt4-{scheme}"]], tmp_path)
    before, ref_before = _input_digests(tgt4), file_digests(Path(ref4))
    r2, r4 = _run_both(ref2, tgt2, ref4 if reference == "v4" else ref2, tgt4)
    assert [g["field"] for g in r4["groups"]] == [g["field"] for g in r2["groups"]]
    assert max(g["chunks"] for g in r4["groups"]) > 1
    assert [g["wraps"] for g in r4["groups"]] == [g["wraps"] for g in r2["groups"]]
    window = r4["phase_referencing"]["methods"]["PWC_DATA"][0]
    assert window["integers"]["rule"] == "delay"
    assert window["integers"]["calibrator"]["nonzero"] > 0     # the slews moved the counts
    assert window["integers"]["target"]["nonzero"] > 0
    # the same scans, integers, antenna solutions and flags counted
    assert _step_entry(r4) == _step_entry(r2)
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")
    assert _input_digests(tgt4) == before
    assert file_digests(Path(ref4)) == ref_before


def test_a_rerun_with_overwrite_writes_the_same_groups(sfpr, tmp_path):
    """A second run over the first's groups (--overwrite: they are unregistered, then
    staged afresh) steps from its own transfer, not the first run's output."""
    ref2, tgt2, ref4, tgt4 = copies_of([sfpr["ref2"], sfpr["tgt2"], sfpr["ref4-fields"],
                                        sfpr["tgt4-fields"]], tmp_path)
    r2, first = _run_both(ref2, tgt2, ref4, tgt4)
    again = calibrate_flat(ref4, tgt4, method=",".join(METHODS), no_verdict=True,
                           calibrator_field="CAL", ref_model_column="MODEL_DATA",
                           chunk_rows=200, overwrite=True)
    assert _step_entry(again) == _step_entry(first) == _step_entry(r2)
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")


def test_calibrator_step_after_the_workers_wrote_the_chunks(sfpr, tmp_path):
    """With a cluster the workers write the transfer's chunks; the step then reads them
    back on the client from the same staged arrays."""
    distributed = pytest.importorskip("distributed")
    ref2, tgt2, ref4, tgt4 = copies_of([sfpr["ref2"], sfpr["tgt2"], sfpr["ref4-fields"],
                                      sfpr["tgt4-fields"]], tmp_path)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        r2 = calibrate_flat(ref2, tgt2, method=",".join(METHODS), no_verdict=True,
                            calibrator_field="CAL", ref_model_column="MODEL_DATA",
                            chunk_rows=200)
        r4 = calibrate_flat(ref4, tgt4, method=",".join(METHODS), no_verdict=True,
                            calibrator_field="CAL", ref_model_column="MODEL_DATA",
                            chunk_rows=200, scheduler=cluster.scheduler_address)
        assert "hitops-write" in set(cluster.scheduler.task_prefixes)
    assert _step_entry(r4) == _step_entry(r2)
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")


def test_an_antenna_unsolved_on_the_calibrator_is_flagged_in_every_group(sfpr, tmp_path):
    """Station GL flagged on every calibrator row of the target band: the step has no
    solution for it and flags its target rows, through each method's own flags, as the
    v2 step flags them in the one FLAG.  PB's first calibrator scan is flagged whole in
    the reference band, so the transfer flags samples the input did not: the step must
    sum and flag with the flags the run staged, not the input's."""
    from casacore import tables as pt

    ref2, tgt2 = copies_of([sfpr["ref2"], sfpr["tgt2"]], tmp_path)
    for ms, station, field, scans in ((tgt2, "GL", "CAL", None), (ref2, "PB", "CAL", 1)):
        with pt.table(ms, readonly=False, ack=False) as t:
            ant = list(pt.table(f"{ms}::ANTENNA", ack=False).getcol("NAME")).index(station)
            fid = list(pt.table(f"{ms}::FIELD", ack=False).getcol("NAME")).index(field)
            hit = ((t.getcol("ANTENNA1") == ant) | (t.getcol("ANTENNA2") == ant)) \
                & (t.getcol("FIELD_ID") == fid)
            if scans is not None:
                scan = t.getcol("SCAN_NUMBER")
                hit &= scan == np.unique(scan[hit])[0]
            flag = t.getcol("FLAG")
            flag[hit] = True
            t.putcol("FLAG", flag)
    tgt4 = _convert(tgt2, tmp_path / "tgt-gl.ps.zarr", True)
    ref4 = _convert(ref2, tmp_path / "ref-gl.ps.zarr", True)
    r2, r4 = _run_both(ref2, tgt2, ref4, tgt4)
    window = r4["phase_referencing"]["methods"]["CWU_DATA"][0]
    assert window["target_rows_flagged"] > 0
    assert _step_entry(r4) == _step_entry(r2)
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")


@pytest.fixture(scope="module")
def one_channel(tmp_path_factory):
    """The packaged phaseref scene with one 230-GHz channel, 20 minutes, no slews and one
    troposphere (as tests/test_phase_referencing.py's one_channel_pair), both formats."""
    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    scene = copy.deepcopy(load_scene_mapping("phaseref")[0])
    scene["observation"]["duration"] = 1200
    scene["corruptions"]["noise"] = False
    scene["bands"][1]["n_chan"] = 1
    scene["observation"]["scan_gap"] = 0
    scene["calibrator"].pop("own_troposphere")
    root = tmp_path_factory.mktemp("v4onechan")
    sets = simulate(scene, root)
    _flag_some(sets["86"], sets["230"])
    return (str(sets["86"]), str(sets["230"]), _convert(sets["86"], root / "ref.ps.zarr", True),
            _convert(sets["230"], root / "tgt.ps.zarr", True))


def test_one_channel_step_carries_the_count_read_from_the_v4_reference(one_channel, tmp_path):
    ref2, tgt2, ref4, tgt4 = copies_of(one_channel, tmp_path)
    flags = dict(method="pwc", no_verdict=True, calibrator_field="3C273",
                 ref_model_column="MODEL_DATA", chunk_rows=300)
    r2 = calibrate_flat(ref2, tgt2, **flags)
    r4 = calibrate_flat(ref4, tgt4, **flags)
    window = r4["phase_referencing"]["methods"]["PWC_DATA"][0]
    assert window["integers"]["rule"] == "carried" and window["switches"]["scan_starts"] > 0
    assert _step_entry(r4) == _step_entry(r2)
    assert_group_equals_column(tgt4, "pwc", tgt2, "PWC_DATA")


@pytest.mark.parametrize("options, expect", [
    (dict(calibrator_field="NOPE"), "--calibrator-field NOPE: no such field"),
    (dict(calibrator_field="CAL", calibrator_model_column="CAL_MODEL",
          ref_model_column="MODEL_DATA"), "--calibrator-model-column CAL_MODEL"),
    (dict(calibrator_field="CAL", ref_model_column="MODEL_DATA",
          export_uvfits="never-written.uvfits"), "a UVFITS file holds one"),
], ids=["no-such-field", "no-such-model", "export-of-two-fields"])
def test_bad_calibrator_input_is_one_line_and_the_store_as_it_was(sfpr, tmp_path, options,
                                                                   expect):
    ref4, tgt4 = copies_of([sfpr["ref4-fields"], sfpr["tgt4-fields"]], tmp_path)
    before = file_digests(Path(tgt4))
    with pytest.raises(HitopsError) as err:    # the CLI's one line: tests/test_cli*.py
        calibrate_flat(ref4, tgt4, no_verdict=True, **options)
    assert expect in str(err.value) and "\n" not in str(err.value)
    assert file_digests(Path(tgt4)) == before
