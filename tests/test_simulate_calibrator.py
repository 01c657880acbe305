"""hitops simulate's resolved calibrator (issue 38): ``calibrator.components`` enter the
calibrator's visibilities and its model is written to MODEL_DATA of both sets.

The truth is computed here from the stored UVW and CHAN_FREQ, independently of
hitops/simulate/sources.py: a 1-Jy point at the phase centre and a point of 0.6 Jy at
(l, m) = (+120, -80) uas gives V = 1 + 0.6 exp(+2 pi i (u l + v m)) (the simulator's
convention, docs/simulate.md "Source models", u, v in wavelengths of each channel).
"""

from __future__ import annotations

import numpy as np
import pytest
from casacore import tables as pt

from hitops.errors import SceneError
from hitops.simulate import simulate
from hitops.simulate.scene import load_scene_mapping, parse_scene

UAS = np.radians(1.0 / 3600e6)
C = 299792458.0
OFFSET_UAS = (120.0, -80.0)
SECOND = {"86": 0.6, "230": 0.6}


def _scene(components=True):
    scene = load_scene_mapping("phaseref")[0]
    scene["observation"].update(duration=600, scan_gap=30, correlations=["RR", "RL", "LR", "LL"])
    scene["corruptions"].update(noise=False, troposphere=False)
    scene["stations"] = ["AP", "PV", "GL"]
    scene["calibrator"]["flux"] = {"86": 1.0, "230": 1.0}
    scene["calibrator"].pop("components", None)     # the packaged scene's own
    if components:
        scene["calibrator"]["components"] = [
            {"flux": SECOND, "offset_ra": OFFSET_UAS[0], "offset_dec": OFFSET_UAS[1],
             "fwhm_major": 0.0}]
    return scene


@pytest.fixture(scope="module")
def resolved(tmp_path_factory):
    return simulate(_scene(), tmp_path_factory.mktemp("resolved"))


def _columns(ms):
    with pt.table(ms, ack=False) as t:
        out = {c: t.getcol(c) for c in ("FIELD_ID", "UVW", "DATA", "MODEL_DATA", "DATA_DESC_ID")}
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        out["CHAN_FREQ"] = t.getcol("CHAN_FREQ")
    return out


@pytest.mark.parametrize("band", ["86", "230"])
def test_model_data_is_the_resolved_calibrator(resolved, band):
    col = _columns(str(resolved[band]))
    cal, target = col["FIELD_ID"] == 1, col["FIELD_ID"] == 0
    assert cal.any() and target.any()
    freq = col["CHAN_FREQ"][col["DATA_DESC_ID"]]                     # (n_row, n_chan)
    u = col["UVW"][:, 0, None] * freq / C
    v = col["UVW"][:, 1, None] * freq / C
    truth = 1.0 + SECOND[band] * np.exp(2j * np.pi * (u * OFFSET_UAS[0] * UAS
                                                      + v * OFFSET_UAS[1] * UAS))
    model, data = col["MODEL_DATA"], col["DATA"]
    # resolved: the calibrator's amplitude is not that of a point
    assert np.ptp(np.abs(truth[cal])) > 0.5
    for hand in (0, 3):                                              # RR, LL
        np.testing.assert_allclose(model[cal][:, :, hand], truth[cal], atol=2e-6)
        # noise-free, no troposphere, no instrumental term: DATA is the sky
        np.testing.assert_allclose(data[cal][:, :, hand], truth[cal], atol=2e-6)
        # the target's rows: CASA's default model, 1
        np.testing.assert_array_equal(model[target][:, :, hand], 1.0)
    # a Stokes I model has nothing in the cross hands
    assert not model[:, :, 1:3].any()


def test_no_components_no_model_column(tmp_path):
    paths = simulate(_scene(components=False), tmp_path)
    for band in ("86", "230"):
        with pt.table(str(paths[band]), ack=False) as t:
            assert "MODEL_DATA" not in t.colnames()
            cal = t.getcol("FIELD_ID") == 1
            np.testing.assert_allclose(t.getcol("DATA")[cal][:, :, 0], 1.0, atol=1e-6)


@pytest.mark.parametrize("value, where", [
    ("a point", r"calibrator\.components"),
    ([{"offset_ra": 10}], r"calibrator\.components\[0\]\.flux"),
    ([{"flux": {"86": 1, "230": 1}, "shape": "square"}], r"calibrator\.components\[0\]\.shape"),
])
def test_bad_components_are_named(value, where):
    scene = _scene(components=False)
    scene["calibrator"]["components"] = value
    with pytest.raises(SceneError, match=where):
        parse_scene(scene)


def test_slews_as_the_schedule_says(resolved):
    """120-s target scans and 60-s calibrator scans alternate, 30 s of nothing (the slew,
    observation.scan_gap) between the end of one scan and the start of the next."""
    with pt.table(str(resolved["230"]), ack=False) as t:
        time, scan = t.getcol("TIME"), t.getcol("SCAN_NUMBER")
        field, interval = t.getcol("FIELD_ID"), t.getcol("INTERVAL")[0]
    numbers = np.unique(scan)
    assert numbers.size >= 3
    starts = np.array([time[scan == s].min() - interval / 2 for s in numbers])
    ends = np.array([time[scan == s].max() + interval / 2 for s in numbers])
    np.testing.assert_allclose(starts[1:] - ends[:-1], 30.0, atol=1e-3)
    fields = [int(np.unique(field[scan == s])[0]) for s in numbers]
    assert fields[:3] == [0, 1, 0]
    np.testing.assert_allclose((ends - starts)[:2], [120.0, 60.0], atol=1e-3)
