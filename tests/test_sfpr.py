"""Source-frequency phase referencing as it is observed (issue 38): the calibrator step on a
pair casatools.simulator laid out (hitops/testing/phaseref_scene.py), whose truth is the
physics alone: each line of sight its own troposphere (a shared part and its own), slews of
60 and 90 s, per-station instrumental phases, delays and drifts in both bands, a resolved
calibrator whose model is in MODEL_DATA of both sets, noise-free."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate
from hitops.testing.phaseref_scene import PhaserefSpec, make_phaseref_pair, target_coherence

#: what the step must reach on every target baseline x channel x hand, noise-free (issue 38)
COHERENCE = 0.99


@pytest.fixture(scope="module", params=[60.0, 90.0], ids=["slew60", "slew90"])
def scene(request, tmp_path_factory):
    return make_phaseref_pair(tmp_path_factory.mktemp(f"sfpr{int(request.param)}"),
                              PhaserefSpec(slew_s=request.param))


def _copy(scene, tmp_path: Path):
    ref, tgt = tmp_path / "ref.ms", tmp_path / "target.ms"
    shutil.copytree(scene.ref_ms, ref)
    shutil.copytree(scene.target_ms, tgt)
    return str(ref), str(tgt)


def test_scene_is_what_the_schedule_says(scene):
    """Slews as scheduled, the calibrator resolved (closure phases in its model), the
    target's model a point, DATA / MODEL_DATA the instrument and troposphere alone."""
    with pt.table(str(scene.target_ms), ack=False) as t:
        time, field = t.getcol("TIME"), t.getcol("FIELD_ID")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        model = t.getcol("MODEL_DATA")
    steps = np.diff(np.unique(time))
    gaps = steps[steps > 2 * scene.spec.integration_s]
    assert np.allclose(gaps, scene.spec.slew_s + scene.spec.integration_s)
    assert np.all(model[field == 0] == 1)
    # closure phase of the calibrator's model on the triangle PB-AP-GL over the track
    cal = (field == 1)
    side = {(p, q): model[cal & (a1 == p) & (a2 == q), 0, 0] for p, q in ((1, 2), (2, 3), (1, 3))}
    closure = np.angle(side[1, 2] * side[2, 3] * np.conj(side[1, 3]))
    assert np.degrees(np.abs(closure)).max() > 30.0


def test_transfer_alone_leaves_the_instrumental_term(scene, tmp_path):
    ref, tgt = _copy(scene, tmp_path)
    calibrate(ref, tgt, method="pwc", no_verdict=True)
    assert target_coherence(Path(tgt), "PWC_DATA").min() < 0.5
