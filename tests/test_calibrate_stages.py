"""Stages of ``hitops calibrate`` tested one at a time (hitops/calibrate/stages.py).

The stage fixtures of tests/conftest.py run stages 1-3 on a synthetic pair whose
layout and phases are known from its PairSpec (hitops/testing/pairs.py), so each
stage's hand-off is checked against that truth without a whole run.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate.modes import REFUSED, Mode, check_options, mode_of
from hitops.errors import InputError
from hitops.testing import PairSpec
from hitops.testing.pairs import expected_pwc_phase, wrap

SPEC = PairSpec(n_time=300, n_scans=2, seed=4)

#: flags that make each declared refusal apply (its mode's own flag added below)
TRIGGERS = {
    "--caltable without --tracker antenna": {"caltable": "x.G", "tracker": "count"},
    "--method cwu": {"method": "cwu"},
    "the n0 step without --method pwc": {"method": "cfpt", "offset_model": "point"},
    "--calibrator-field": {"calibrator_field": "CAL"},
    "--ref-model-column": {"ref_model_column": "MODEL_DATA"},
    "--ratio": {"ratio": 2.5},
    "--average-channels": {"average_channels": True},
    "--scheduler on a Measurement Set v2 target": {"scheduler": "tcp://x:8786"},
    "--tracker other than count": {"tracker": "smooth"},
    "the n0 step": {"offset_model": "point"},
    "--calibrator-model-column without --calibrator-field": {"calibrator_model_column": "MODEL_DATA"},
}
MODE_FLAGS = {Mode.VISIBILITIES: {}, Mode.TABLE: {"reference_table": "ref.fringe"},
              Mode.CALIBRATOR: {"calibrator_field": "CAL"}}


@pytest.mark.parametrize("mode,refused", [(m, r) for m, rows in REFUSED.items() for r in rows],
                         ids=lambda x: getattr(x, "option", getattr(x, "value", None)))
def test_stage1_every_declared_refusal_is_reached(calibrate_options, mode, refused):
    # each row of the table refuses on its own (an unreachable row would be a dead rule),
    # before any set is opened: the paths do not exist
    opts = calibrate_options("/nonexistent/ref.ms", "/nonexistent/tgt.ms",
                             **{**MODE_FLAGS[mode], **TRIGGERS[refused.option]})
    assert mode_of(opts) is mode
    methods = opts.output.method.split(",")
    with pytest.raises(InputError) as err:
        check_options(opts, methods)
    assert str(err.value) == refused.why(opts, methods)


def test_stage1_what_a_mode_accepts_passes(calibrate_options):
    for mode, flags in MODE_FLAGS.items():
        opts = calibrate_options("/nonexistent/ref.ms", "/nonexistent/tgt.ms", **flags)
        assert check_options(opts, ["pwc"]) is mode
    # the antenna tracker and the n0 step in the visibility mode; a caltable with antenna
    opts = calibrate_options("a", "b", tracker="antenna", offset_model="point", caltable="x.G")
    assert check_options(opts, ["pwc"]) is Mode.VISIBILITIES


def test_stage3_the_plan_is_the_pairs_layout(planned_run):
    n_bl = SPEC.n_ant * (SPEC.n_ant - 1) // 2
    chunk_rows = 50 * n_bl                         # 50 of the 300 times per chunk
    planned = planned_run(SPEC, method="pwc,cfpt", chunk_rows=chunk_rows)
    run = planned.plan
    assert run.methods == ["pwc", "cfpt"]
    assert run.outputs == {"pwc": "PWC_DATA", "cfpt": "CFPT_DATA"}
    assert len(run.groups) == 1
    group = run.groups[0]
    # R from the two sets' frequencies, split into its integer and fractional parts
    assert group.ratio == pytest.approx(SPEC.ratio, rel=1e-12)
    assert group.r == math.floor(SPEC.ratio)
    assert group.eps == pytest.approx(SPEC.ratio - math.floor(SPEC.ratio), abs=1e-12)
    assert group.n_chunks == SPEC.n_time // 50
    assert len(group.grid.times) == SPEC.n_time
    assert len(set(group.grid.scans.scan_numbers.tolist())) == SPEC.n_scans
    assert len(group.antenna_names) == SPEC.n_ant
    assert group.n_matched == SPEC.n_time * n_bl


def test_stage4_stages_the_paper_output_and_rollback_leaves_the_set(planned_copy):
    from hitops.calibrate.output import OutputTransaction
    from hitops.calibrate.passes import run_group

    planned = planned_copy(SPEC, method="pwc", chunk_rows=1200)
    run, truth = planned.plan, planned.truth
    tx = OutputTransaction(run.target_ms, run.outputs, run.columns.target_data, None,
                           run.chunk_rows)
    tx.create_columns()
    try:
        result = run_group(run, run.groups[0], tx, None)
        with pt.table(str(truth.target_ms), ack=False) as t:
            staged = t.getcol(tx.staging["pwc"])
        # the paper's PWC: the source phase less 2 pi eps n0 per baseline and scan
        phase = np.angle(staged[:, 0, :])
        assert np.max(np.abs(wrap(phase - expected_pwc_phase(truth)))) < 1e-5
        assert result is not None
    finally:
        del run
        tx.rollback()
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert not any(c.startswith("HITOPS_PARTIAL") or c == "PWC_DATA" for c in t.colnames())


def test_stage4_the_first_pass_starts_from_the_planning_tracker(planned_run):
    """The tracker that plans the reads has an empty state until a pass tracks with it:
    the first pass starts from it (an antenna tracker's whole-track records are then held
    once, not twice), later passes from fresh ones; what it plans is the same after."""
    from hitops.calibrate.output import OutputTransaction
    from hitops.calibrate.pipeline import GroupPipeline, PassSpec

    planned = planned_run(SPEC, method="pwc", tracker="antenna", chunk_rows=1200)
    run = planned.plan
    # a first pass writes nothing: the transaction is never staged
    tx = OutputTransaction(run.target_ms, run.outputs, run.columns.target_data, None,
                           run.chunk_rows)
    pipeline = GroupPipeline(run, run.groups[0], tx, None)
    try:
        plan_tracker = pipeline.plan_tracker
        bounds = run.groups[0].bounds
        extents = [plan_tracker.extended(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        assert np.all(np.isnan(plan_tracker.antenna_phase))       # nothing tracked yet
        first = pipeline.run_pass(PassSpec(write=False))
        assert first.tracker is plan_tracker
        assert np.any(np.isfinite(plan_tracker.antenna_phase))     # the pass filled it
        assert [plan_tracker.extended(a, b) for a, b in zip(bounds[:-1], bounds[1:])] == extents
        second = pipeline.start_state().result.tracker
        assert second is not plan_tracker and np.all(np.isnan(second.antenna_phase))
    finally:
        pipeline.close()
