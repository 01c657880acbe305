"""Three bands (86, 230, 345 GHz) through one troposphere, and hitops calibrate on every pair."""

from __future__ import annotations

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.simulate import parse_scene, simulate
from hitops.simulate.scene import load_scene_mapping


def triband_small() -> dict:
    """The demo stations, 20 min of 2 s integrations, 86/230/345 GHz, no noise; turbulence slow enough that even 230 GHz keeps the Itoh condition."""
    scene, _ = load_scene_mapping("demo")
    scene["observation"].update({"duration": 1200, "integration": 2})
    scene["observation"].pop("scan_length")
    scene["observation"].pop("scan_gap")
    scene["bands"].append({"name": "345", "freq_ghz": 345, "bandwidth_ghz": 2})
    scene["source"]["flux"]["345"] = 0.9
    scene["corruptions"].update({"noise": False, "coherence_scale": 2.0})
    return scene


def phases(ms, column):
    with pt.table(str(ms), ack=False) as t:
        data = t.getcol(column)[:, 0, 0]
        a1, a2, time = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("TIME")
    return np.angle(data), a1, a2, time


def wrap(x):
    return np.angle(np.exp(1j * x))


@pytest.fixture(scope="module")
def triband(tmp_path_factory):
    out = tmp_path_factory.mktemp("triband")
    return simulate(triband_small(), out, save_truth=True)


def test_one_ms_per_band_same_troposphere(triband):
    assert {"86", "230", "345"} <= set(triband)
    truth = np.load(triband["truth"])
    np.testing.assert_allclose(truth["phase_345"], 1.5 * truth["phase_230"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(truth["phase_345"], (345 / 86) * truth["phase_86"], rtol=1e-12,
                               atol=1e-12)
    for band in ("86", "230", "345"):
        with pt.table(str(triband[band]) + "::SPECTRAL_WINDOW", ack=False) as spw:
            assert spw.getcol("REF_FREQUENCY")[0] == pytest.approx(float(band) * 1e9)


@pytest.mark.parametrize("ref,target,column", [("86", "230", "PWC_DATA"), ("86", "345", "PWC86_DATA"),
                                               ("230", "345", "PWC230_DATA")])
def test_calibrate_every_pair_of_the_triband_output(triband, tmp_path, ref, target, column):
    """PWC on noise-free data leaves exactly zero phase (all stations up from the start: n0 = 0)."""
    report = calibrate_flat(str(triband[ref]), str(triband[target]), method="pwc", output_column=column,
                       overwrite=True, report=str(tmp_path / f"{ref}-{target}.json"))
    assert report                                   # the run's JSON report
    phase, *_ = phases(triband[target], column)
    raw, *_ = phases(triband[target], "DATA")
    assert np.abs(raw).max() > 1.0                  # the troposphere is there before ...
    assert np.abs(wrap(phase)).max() < 1e-4         # ... and gone after PWC


def test_230_to_345_cfpt_jumps_by_pi_at_every_wrap(triband, tmp_path):
    """R = 1.5: eps = 1/2, so CFPT leaves a jump of exactly pi at each 230 GHz wrap."""
    calibrate_flat(str(triband["230"]), str(triband["345"]), method="cfpt", output_column="CFPT230_DATA",
              overwrite=True, report=str(tmp_path / "cfpt.json"))
    phase, a1, a2, time = phases(triband["345"], "CFPT230_DATA")
    ref_phase, *_ = phases(triband["230"], "DATA")
    sel = (a1 == 0) & (a2 == 1)
    res = phase[sel]
    # every residual is 0 or pi
    assert np.all(np.minimum(np.abs(wrap(res)), np.abs(wrap(res - np.pi))) < 1e-4)
    jumps = np.abs(wrap(np.diff(res))) > np.pi / 2
    wraps = np.abs(np.diff(ref_phase[sel])) > np.pi
    assert wraps.sum() > 5
    np.testing.assert_array_equal(jumps, wraps)


def test_packaged_triband_scene_parses_with_weather():
    scene = parse_scene("triband")
    assert [b.name for b in scene.bands] == ["86", "230", "345"]
    assert all(s.weather is not None and "345" in s.weather.bands for s in scene.stations)
