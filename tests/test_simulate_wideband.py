"""hitops simulate, wideband: windows and channels, excess-path troposphere, instrumental
phase and delay, per-channel noise, resolved sources (truth from physics)."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from casacore import tables as pt

from hitops.errors import SceneError
from hitops.simulate import parse_scene, simulate
from test_simulate import small_scene  # tests/ is on sys.path (rootdir-relative)

C = 299792458.0
BOLTZMANN = 1.380649e-23
WIDE_230 = {"name": "230", "freq_ghz": 230, "bandwidth_ghz": 2, "n_chan": 16,
            "windows_ghz": [227.1, 229.1]}
WIDE_86 = {"name": "86", "freq_ghz": 86, "bandwidth_ghz": 2, "n_chan": 16}


def wide_scene(minutes=20, **changes) -> dict:
    """The demo scene, 20 minutes, 86 GHz one 16-channel window, 230 GHz two windows."""
    scene = small_scene(bands=[dict(WIDE_86), dict(WIDE_230)], **changes)
    scene["observation"]["duration"] = minutes * 60
    return scene


def main_table(ms: Path, *cols):
    with pt.table(str(ms), ack=False) as t:
        return [t.getcol(c) for c in cols]


def channel_freqs(ms: Path) -> np.ndarray:
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        return t.getcol("CHAN_FREQ")


@pytest.fixture(scope="module")
def tropo_wide(tmp_path_factory):
    """Noise-free point source behind a troposphere, with the truth file."""
    out = tmp_path_factory.mktemp("tropo-wide")
    scene = wide_scene(corruptions={"noise": False, "seed": 5, "coherence_scale": 0.5})
    return simulate(scene, out, save_truth=True), parse_scene(scene)


def test_layout_one_spectral_window_per_window(tropo_wide):
    paths, scene = tropo_wide
    ms = paths["230"]
    freq = channel_freqs(ms)
    np.testing.assert_allclose(freq[:, 0], [226.1e9 + 62.5e6, 228.1e9 + 62.5e6])
    np.testing.assert_allclose(np.diff(freq, axis=1), 125e6)
    with pt.table(f"{ms}::DATA_DESCRIPTION", ack=False) as t:
        assert t.getcol("SPECTRAL_WINDOW_ID").tolist() == [0, 1]
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        assert t.getcol("NUM_CHAN").tolist() == [16, 16]
        np.testing.assert_allclose(t.getcol("TOTAL_BANDWIDTH"), 2e9)
        np.testing.assert_allclose(t.getcol("REF_FREQUENCY"), freq[:, 0])
    data, ddid, time, ant1, ant2 = main_table(ms, "DATA", "DATA_DESC_ID", "TIME", "ANTENNA1",
                                              "ANTENNA2")
    (data86,) = main_table(paths["86"], "DATA")
    assert data.shape == (2 * data86.shape[0], 16, 2) and data86.shape[1:] == (16, 2)
    assert np.all(np.diff(time) >= 0), "rows are in time order"
    # each time holds every baseline once per window, window 0 first
    for w in (0, 1):
        keys = time[ddid == w] * 100 + ant1[ddid == w] * 10 + ant2[ddid == w]
        assert np.unique(keys).size == keys.size == data86.shape[0]
    first = time == time[0]
    assert ddid[first].tolist() == sorted(ddid[first].tolist())


def test_channel_phase_is_its_frequency_times_the_excess_path(tropo_wide):
    """phase_k = 2 pi nu_k dL / c on every channel; one ratio per window would be wrong."""
    paths, scene = tropo_wide
    truth = np.load(paths["truth"])
    path = truth["path_m"]
    for band in ("86", "230"):
        ms = paths[band]
        data, ddid, time, ant1, ant2 = main_table(ms, "DATA", "DATA_DESC_ID", "TIME",
                                                  "ANTENNA1", "ANTENNA2")
        t_index = np.searchsorted(truth["time"], time)
        d_path = path[ant1, t_index] - path[ant2, t_index]
        freq = channel_freqs(ms)[ddid]                              # (n_row, n_chan)
        expected = 2 * np.pi * freq * d_path[:, None] / C
        for c in range(2):
            residual = np.angle(data[:, :, c] * np.exp(-1j * expected))
            assert np.abs(residual).max() < 2e-5
        # channel k against channel 0 of its window: phase_k = (nu_k / nu_0) phase_0
        phase0 = 2 * np.pi * freq[:, :1] * d_path[:, None] / C
        ratio = np.angle(data[:, :, 0] * np.exp(-1j * phase0 * freq / freq[:, :1]))
        assert np.abs(ratio).max() < 2e-5
        # a plausible wrong model: every channel of a window at the window's centre frequency
        centre = freq.mean(axis=1, keepdims=True)
        wrong = np.angle(data[:, :, 0] * np.exp(-2j * np.pi * centre * d_path[:, None] / C))
        assert np.abs(wrong[:, [0, -1]]).max() > 0.05
    assert np.ptp(path) > 1e-3, "the excess path must move by millimetres for the test to bite"


def _sefd(t_rx, diameter, efficiency):
    return 2 * BOLTZMANN * t_rx / (efficiency * np.pi * diameter ** 2 / 4) / 1e-26


def test_per_channel_noise_follows_the_radiometer_equation(tmp_path):
    """tau = 0, so T_sys = T_rx: sigma = sqrt(SEFD_p SEFD_q / (2 dnu_chan dt)) / eta_q."""
    stations = [{"code": c, "bands": {"86": {"tau": 0.0}, "230": {"tau": 0.0}}}
                for c in ("AP", "PV", "GL", "PB", "KP")]
    scene = wide_scene(minutes=30, corruptions={"troposphere": False, "seed": 3},
                       stations=stations)
    paths = simulate(scene, tmp_path)
    parsed = parse_scene(scene)
    ms = paths["230"]
    data, sigma, ant1, ant2 = main_table(ms, "DATA", "SIGMA", "ANTENNA1", "ANTENNA2")
    residual = data - 1.0                                   # the 1 Jy point source
    dnu = 125e6
    for p, q in ((0, 1), (1, 3), (2, 4)):
        sp, sq = (parsed.stations[i] for i in (p, q))
        sefd_p = _sefd(sp.bands["230"].t_rx, sp.diameter, sp.bands["230"].aperture_efficiency)
        sefd_q = _sefd(sq.bands["230"].t_rx, sq.diameter, sq.bands["230"].aperture_efficiency)
        expected = np.sqrt(sefd_p * sefd_q / (2 * dnu * 2.0)) / 0.88
        rows = (ant1 == p) & (ant2 == q)
        np.testing.assert_allclose(sigma[rows], expected, rtol=1e-5)
        for k in (0, 7, 15):
            for part in (residual[rows, k].real, residual[rows, k].imag):
                # ~1800 samples: the rms is known to ~2.4% (1 sigma)
                assert abs(part.std() / expected - 1) < 0.08
        # the window's bandwidth instead of the channel's would be 4x too small
        assert residual[rows].real.std() > 3 * expected / 4
    # channels are independent: neighbours uncorrelated
    rows = (ant1 == 0) & (ant2 == 1)
    corr = np.corrcoef(residual[rows, 3, 0].real, residual[rows, 4, 0].real)[0, 1]
    assert abs(corr) < 0.1


def test_closure_phases_of_a_two_component_source(tmp_path):
    """Point (1 Jy) + point (0.8 Jy, 80 uas E, 60 uas N) behind a troposphere and instrumental
    delays: closure phases equal the analytic two-point value on every channel."""
    offset_l, offset_m = 80.0, 60.0
    scene = wide_scene(corruptions={"noise": False, "seed": 9})
    scene["source"]["components"] = [{"flux": {"86": 0.8, "230": 0.8}, "fwhm_major": 0,
                                      "offset_ra": offset_l, "offset_dec": offset_m}]
    scene["stations"] = ["AP", {"code": "PV", "bands": {"230": {"instrumental": {
        "phase_deg": 40, "delay_ns": 0.3}}}}, "GL", "PB", "KP"]
    paths = simulate(scene, tmp_path)
    ms = paths["230"]
    data, uvw, ddid, time, ant1, ant2 = main_table(ms, "DATA", "UVW", "DATA_DESC_ID", "TIME",
                                                   "ANTENNA1", "ANTENNA2")
    freq = channel_freqs(ms)
    uas = np.radians(1 / 3600e6)
    n_checked, largest = 0, 0.0
    for t in np.unique(time)[::50]:
        for w in (0, 1):
            sel = (time == t) & (ddid == w)
            rows = {(a, b): i for a, b, i in zip(ant1[sel], ant2[sel], np.flatnonzero(sel))}
            for a, b, c in ((0, 1, 2), (1, 2, 3), (0, 3, 4)):
                if not {(a, b), (b, c), (a, c)} <= set(rows):
                    continue
                r_ab, r_bc, r_ac = rows[a, b], rows[b, c], rows[a, c]
                measured = np.angle(data[r_ab, :, 0] * data[r_bc, :, 0] * np.conj(data[r_ac, :, 0]))

                def model(r):
                    u = uvw[r, 0] * freq[w] / C
                    v = uvw[r, 1] * freq[w] / C
                    return 1.0 + 0.8 * np.exp(2j * np.pi * (u * offset_l + v * offset_m) * uas)

                analytic = np.angle(model(r_ab) * model(r_bc) * np.conj(model(r_ac)))
                np.testing.assert_allclose(np.angle(np.exp(1j * (measured - analytic))), 0,
                                           atol=1e-4)
                largest = max(largest, np.abs(analytic).max())
                n_checked += 1
    assert n_checked > 20
    assert largest > 0.3, "closure phases are not zero"


def test_ring_matches_a_sum_of_points_on_a_circle(tmp_path):
    """A thin ring (40 uas) against 720 points on a circle summed directly."""
    scene = wide_scene(minutes=6, corruptions={"noise": False, "troposphere": False})
    scene["source"]["flux"] = {"86": 0.0, "230": 0.0}
    scene["source"]["components"] = [{"shape": "ring", "diameter": 40.0, "width": 0.0,
                                      "flux": {"86": 1.0, "230": 1.0}, "offset_ra": 5.0}]
    paths = simulate(scene, tmp_path)
    data, uvw, ddid = main_table(paths["230"], "DATA", "UVW", "DATA_DESC_ID")
    freq = channel_freqs(paths["230"])
    uas = np.radians(1 / 3600e6)
    angle = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    l = (5.0 + 20.0 * np.sin(angle)) * uas
    m = (20.0 * np.cos(angle)) * uas
    rows = np.arange(0, data.shape[0], 97)
    for r in rows:
        u = uvw[r, 0] * freq[ddid[r]] / C
        v = uvw[r, 1] * freq[ddid[r]] / C
        points = np.exp(2j * np.pi * (u[:, None] * l + v[:, None] * m)).mean(axis=1)
        np.testing.assert_allclose(data[r, :, 0], points, atol=2e-5)
    assert np.abs(data[rows, :, 0]).min() < 0.3, "long baselines reach the ring's first null"


def test_instrumental_phase_and_delay_drift(tmp_path):
    """phase_pq(nu, t) = phi_p(t) + 2 pi (nu - nu_band) tau_p(t) on a station with both terms."""
    scene = wide_scene(minutes=10, corruptions={"noise": False, "troposphere": False})
    inst = {"phase_deg": 30, "delay_ns": 0.25, "phase_drift_deg_per_hour": 60,
            "delay_drift_ns_per_hour": -0.6}
    scene["stations"] = [{"code": "AP", "bands": {"230": {"instrumental": inst}}},
                         "PV", "GL", "PB", "KP"]
    paths = simulate(scene, tmp_path, save_truth=True)
    truth = np.load(paths["truth"])
    ms = paths["230"]
    data, ddid, time, ant1 = main_table(ms, "DATA", "DATA_DESC_ID", "TIME", "ANTENNA1")
    freq = channel_freqs(ms)
    start = parse_scene(scene).start_mjd_s
    rows = ant1 == 0
    hours = (time[rows] - start) / 3600
    phase = np.radians(30 + 60 * hours)
    delay = (0.25 - 0.6 * hours) * 1e-9
    expected = phase[:, None] + 2 * np.pi * (freq[ddid[rows]] - 230e9) * delay[:, None]
    residual = np.angle(data[rows, :, 0] * np.exp(-1j * expected))
    assert np.abs(residual).max() < 1e-5
    assert "inst_delay_230" in truth.files and "inst_phase_86" not in truth.files
    np.testing.assert_allclose(truth["inst_delay_230"][0, 0], 0.25e-9 - 0.6e-9 * (
        truth["time"][0] - start) / 3600, rtol=1e-9)
    # the other band and the other stations are untouched
    (data86,) = main_table(paths["86"], "DATA")
    assert np.abs(np.angle(data86)).max() < 1e-6


def test_packaged_ngeht_scene():
    scene = parse_scene("ngeht")
    assert [b.name for b in scene.bands] == ["86", "230", "345"]
    total = {b.name: b.n_window * b.bandwidth_hz for b in scene.bands}
    assert total == {"86": 8e9, "230": 16e9, "345": 16e9}     # ngehtsim's ngEHT bandwidths
    freq230 = scene.bands[1].chan_freq()
    assert freq230.shape == (2, 64)
    assert freq230.min() == pytest.approx(209.1e9 + 62.5e6)
    assert freq230.max() == pytest.approx(233.1e9 - 62.5e6)


def test_ngeht_scene_runs_through_the_cli(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "hitops.cli", "simulate", "ngeht", "--outdir",
                           str(tmp_path), "--duration", "300", "--no-noise"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    for band, n_win in (("86", 1), ("230", 2), ("345", 2)):
        freq = channel_freqs(tmp_path / f"sim-{band}.ms")
        assert freq.shape == (n_win, 64)


BAD = [
    ("bands", lambda s: s["bands"][1].update(windows_ghz=[229.1, 227.1]), "bands[1].windows_ghz"),
    ("bands", lambda s: s["bands"][1].update(windows_ghz=[227.1, 228.1]), "bands[1].windows_ghz"),
    ("bands", lambda s: s["bands"][1].update(n_chan=0), "bands[1].n_chan"),
    ("bands", lambda s: s["bands"][1].update(chan_width_mhz=500), "bands[1].chan_width_mhz"),
    ("ring", lambda s: s["source"].update(components=[{"shape": "ring", "flux": {
        "86": 1, "230": 1}}]), "source.components[0].diameter"),
    ("shape", lambda s: s["source"].update(components=[{"shape": "disk", "flux": {
        "86": 1, "230": 1}, "fwhm_major": 3}]), "source.components[0].shape"),
    ("inst", lambda s: s.update(stations=[{"code": "AP", "bands": {"230": {"instrumental": {
        "delay_us": 1}}}}, "PV"]), "stations[0].bands.230.instrumental.delay_us"),
]


@pytest.mark.parametrize("name,change,field", BAD, ids=[f"{b[0]}-{i}" for i, b in enumerate(BAD)])
def test_bad_wideband_scene_names_the_field(tmp_path, name, change, field):
    scene = wide_scene()
    change(scene)
    with pytest.raises(SceneError, match=field.replace(".", r"\.").replace("[", r"\[")
                       .replace("]", r"\]")):
        simulate(copy.deepcopy(scene), tmp_path)
    assert not any(tmp_path.iterdir())
    path = tmp_path / "bad.yml"
    path.write_text(yaml.safe_dump(scene))
    proc = subprocess.run([sys.executable, "-m", "hitops.cli", "simulate", str(path), "--outdir",
                           str(tmp_path / "out")], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert field in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_data_do_not_depend_on_the_block_size(tmp_path, monkeypatch):
    """Blocks of 9 (230 GHz) or 18 (86 GHz) times give the set one block gives."""
    import hitops.simulate.bands as bands

    scene = wide_scene(minutes=4, corruptions={"seed": 4})
    scene["stations"] = ["AP", {"code": "PV", "bands": {"230": {"instrumental": {
        "delay_ns": 0.1, "phase_drift_deg_per_hour": 20}}}}, "GL", "PB", "KP"]
    whole = simulate(scene, tmp_path / "whole")
    monkeypatch.setattr(bands, "BLOCK_VISIBILITIES", 30 * 2 * 16 * 2 * 3)
    blocked = simulate(scene, tmp_path / "blocked")
    for band in ("86", "230"):
        cols = ("DATA", "SIGMA", "TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "UVW")
        for a, b in zip(main_table(whole[band], *cols), main_table(blocked[band], *cols)):
            np.testing.assert_array_equal(a, b)
    assert len(bands.row_blocks(np.repeat(np.arange(120), 10), 35)) == 40
