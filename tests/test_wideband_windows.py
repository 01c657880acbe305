"""Several reference windows feeding several target windows (issue 26), noise-free.

The layout that failed first in the wideband recipe: reference two windows of
16 x 125 MHz at 85 and 87 GHz, target two of 16 x 125 MHz at 227.1 and 229.1 GHz.
Windows pair in frequency order (docs/wideband.md; calibrate/groups.py): 85 -> 227.1,
87 -> 229.1.  There R_0 = 229.1/87 = 79/30 exactly, so the window centre's phase
cannot tell an n0 of k turns from k + 30; a wrong k leaves a delay of 30/nu_ref
across the window (2.2 rad at its edges).  The channels of the window can: a
wrong k turns channel j by 2*pi*(nu_j - nu_0)*k/nu_ref.

The truth is physics, not hitops: the troposphere is an excess path, so every
channel of a point source at the phase centre must come out at one constant phase
(whole-track coherence 1) after PWC with the right n0, and all channels of all
windows at the same phase (the vector average over them 1).  Two layouts:

* ``hitops simulate`` with a scene mapping (5 stations, 20 min at 1 s in four
  5-minute scans, a Kolmogorov troposphere at 0.3 x the stations' coherence time):
  each scan is counted from its own start, by which time the stations' paths differ
  by up to ~38 turns of the 87-GHz phase;
* casatools.simulator (tests/solutions_scene.py; 4 stations, 10 min at 1 s, one
  scan) with per-station paths up to 13 cm apart at the start.

The plausible wrong implementation, the n0 step on each window centre's phase alone
(what calibrate did when the recipe first tried this layout), fails the same checks.
"""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.calibrate.channels import ChannelPlan
from hitops.simulate import simulate
from test_simulate import small_scene  # tests/ is on sys.path (rootdir-relative)

from solutions_scene import C_LIGHT, excess_path, lay_out, write_path_phases

REF_WINDOWS_GHZ = (85.0, 87.0)
TARGET_WINDOWS_GHZ = (227.1, 229.1)
#: the pairing docs/wideband.md states: windows in frequency order
PAIRING_GHZ = list(zip(REF_WINDOWS_GHZ, TARGET_WINDOWS_GHZ))
#: 229.1/87 = 79/30: one channel at the centre cannot tell k from k + 30 turns
LATTICE_PERIOD = 30


def two_window_scene(seed: int = 7) -> dict:
    scene = small_scene(
        bands=[{"name": "86", "freq_ghz": 86, "bandwidth_ghz": 2, "n_chan": 16,
                "windows_ghz": list(REF_WINDOWS_GHZ)},
               {"name": "230", "freq_ghz": 228.1, "bandwidth_ghz": 2, "n_chan": 16,
                "windows_ghz": list(TARGET_WINDOWS_GHZ)}],
        # 0.3 x the coherence time: the paths wander tens of 86-GHz turns in 20 minutes
        # and move at most ~1.6 rad of the 88-GHz phase from one 1-s sample to the next
        corruptions={"noise": False, "seed": seed, "coherence_scale": 0.3})
    scene["observation"].update({"duration": 1200, "integration": 1, "scan_length": 300,
                                 "scan_gap": 60})
    return scene


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """(ref_ms, target_ms, truth) written by hitops simulate."""
    out = tmp_path_factory.mktemp("windows-sim")
    paths = simulate(two_window_scene(), out, save_truth=True)
    return paths["86"], paths["230"], np.load(paths["truth"])


@pytest.fixture(scope="module")
def casa_laid_out(tmp_path_factory):
    """(ref_ms, target_ms, path) laid out by casatools.simulator, the path written by us."""
    root = tmp_path_factory.mktemp("windows-casa")
    ref_ms, target_ms = root / "ref.ms", root / "target.ms"
    stations = ("PV", "PB", "AP", "GL")
    scans = (("M87", 0.0, 600.0),)
    lay_out(ref_ms, [f * 1e9 for f in REF_WINDOWS_GHZ], scans, "2023/04/10/03:00:00", stations)
    lay_out(target_ms, [f * 1e9 for f in TARGET_WINDOWS_GHZ], scans, "2023/04/10/03:00:00",
            stations)
    with pt.table(str(ref_ms), ack=False) as t:
        times = np.unique(t.getcol("TIME"))
    # up to 13 cm apart at the start: 39 turns of the 87-GHz phase
    path = excess_path(times, len(stations), seed=3, scale_m=0.004) + [0.0, 0.091, -0.043, 0.022]
    write_path_phases(ref_ms, times, path)
    write_path_phases(target_ms, times, path)
    return ref_ms, target_ms, path


def _copy(ms, directory):
    directory.mkdir(parents=True, exist_ok=True)
    return shutil.copytree(ms, directory / ms.name)


def coherences(ms, column="PWC_DATA"):
    """Whole-track coherence |mean of V/|V|| per (baseline, window): (n_chan, n_corr), and per
    baseline over every channel and window: (n_corr,)."""
    with pt.table(str(ms), ack=False) as t:
        data, flag = t.getcol(column), t.getcol("FLAG")
        a1, a2, ddid = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("DATA_DESC_ID")
    ok = ~flag & (np.abs(data) > 0)
    unit = np.where(ok, data / np.where(ok, np.abs(data), 1), 0)
    per_channel, per_baseline = {}, {}
    for key in sorted(set(zip(a1, a2, ddid))):
        rows = (a1 == key[0]) & (a2 == key[1]) & (ddid == key[2])
        per_channel[key] = np.abs(unit[rows].sum(axis=0)) / np.maximum(ok[rows].sum(axis=0), 1)
    for key in sorted(set(zip(a1, a2))):
        rows = (a1 == key[0]) & (a2 == key[1])
        per_baseline[key] = (np.abs(unit[rows].sum(axis=(0, 1)))
                             / np.maximum(ok[rows].sum(axis=(0, 1)), 1))
    return per_channel, per_baseline


def centre_channel_only(monkeypatch):
    """The wrong implementation: the n0 step on each window centre's phase alone."""
    monkeypatch.setattr(ChannelPlan, "across_channels", property(lambda self: False))


def _check_all_channels(ms):
    per_channel, per_baseline = coherences(ms)
    worst_channel = min(float(c.min()) for c in per_channel.values())
    worst_baseline = min(float(c.min()) for c in per_baseline.values())
    return worst_channel, worst_baseline


def test_the_simulated_data_are_the_excess_path_and_need_the_step(simulated):
    """Premises from the simulator's truth: every channel's phase is 2*pi*nu_k*dL/c, and some
    scan starts more than half a lattice period (15 turns of 87 GHz) from zero."""
    ref_ms, _, truth = simulated
    with pt.table(str(ref_ms), ack=False) as t:
        data, time, a1, a2, ddid, scan = (t.getcol(c) for c in (
            "DATA", "TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "SCAN_NUMBER"))
    freq = truth["chan_freq_86"][ddid]                                # (n_row, n_chan)
    np.testing.assert_allclose(freq.mean(axis=1) / 1e9, np.array(REF_WINDOWS_GHZ)[ddid])
    it = np.searchsorted(truth["time"], time)
    dl = truth["path_m"][a1, it] - truth["path_m"][a2, it]
    expected = np.exp(2j * np.pi * freq * dl[:, None] / C_LIGHT)
    assert np.abs(np.angle(data[..., 0] * np.conj(expected))).max() < 1e-3
    starts = [time[scan == s].min() for s in np.unique(scan)]
    turns = [np.abs(dl[time == t0]).max() * 87e9 / C_LIGHT for t0 in starts]
    assert max(turns) > LATTICE_PERIOD / 2 + 5


def _run(ref_ms, target_ms, tracker):
    return calibrate_flat(str(ref_ms), str(target_ms), method="pwc", tracker=tracker,
                     offset_model="point", no_verdict=True)


def _offsets(report, window):
    return [abs(e["k"]) for e in report["groups"][window]["offset_step"]["series"]
            if e.get("samples")]


@pytest.mark.parametrize("layout", ["simulated",
                                    pytest.param("casa_laid_out", marks=pytest.mark.slow)])
@pytest.mark.parametrize("tracker", ["antenna", "count"])
def test_two_windows_feed_two_on_every_channel(layout, tracker, request, tmp_path, monkeypatch,
                                               caplog):
    ref_ms, target_ms, _ = request.getfixturevalue(layout)
    target = _copy(target_ms, tmp_path / "all")
    with caplog.at_level(logging.INFO, logger="hitops.calibrate"):
        report = _run(ref_ms, target, tracker)
    # the pairing: frequency order, in the report and in the log
    paired = [(g["ref_freq_hz"] / 1e9, g["target_freq_hz"] / 1e9) for g in report["groups"]]
    np.testing.assert_allclose(paired, PAIRING_GHZ)
    assert ("spectral windows 0 -> 0; field M87, spectral windows 1 -> 1"
            in caplog.text.replace("\n", " "))
    for ref_ghz, target_ghz in PAIRING_GHZ:
        assert f"(from the spectral windows: {target_ghz:g} GHz / {ref_ghz:g} GHz)" in caplog.text
    # the 229.1/87 window needed an n0 beyond what its centre can tell apart
    assert max(_offsets(report, 1)) > LATTICE_PERIOD / 2
    worst_channel, worst_baseline = _check_all_channels(target)
    assert worst_channel >= 0.999
    assert worst_baseline >= 0.99
    # the old step on the window centre alone: right at the centre, wrong across the window
    wrong = _copy(target_ms, tmp_path / "centre")
    with monkeypatch.context() as m:
        centre_channel_only(m)
        _run(ref_ms, wrong, tracker)
    wrong_channel, wrong_baseline = _check_all_channels(wrong)
    # one constant wrong n0 per series keeps each channel coherent over a scan but turns
    # the channels apart; with several scans (n0 per scan) each channel decorrelates too
    # (measured: all channels 0.391-0.964, one channel 0.548-0.837 with four scans)
    assert wrong_baseline < 0.99, wrong_baseline
    if layout == "simulated":
        assert wrong_channel < 0.999, wrong_channel
