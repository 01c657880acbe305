"""hitops simulate: physics (troposphere, noise, frequency scaling), rows, seeds, bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from casacore import tables as pt

from hitops.errors import OutputExistsError, SceneError
from hitops.simulate import parse_scene, simulate
from hitops import radiometer as noise_mod
from hitops.simulate import troposphere as tp
from hitops.simulate.api import observe
from hitops.simulate.scene import load_scene_mapping

HITOPS = [sys.executable, "-m", "hitops.cli"]


def small_scene(**changes) -> dict:
    """The demo scene shortened to 20 minutes of 2 s integrations (fast)."""
    scene, _ = load_scene_mapping("demo")
    scene["observation"].update({"duration": 1200, "integration": 2})
    scene["observation"].pop("scan_length")
    scene["observation"].pop("scan_gap")
    for section, values in changes.items():
        if isinstance(values, dict) and isinstance(scene.get(section), dict):
            scene[section].update(values)
        else:
            scene[section] = values
    return scene


def write_scene(tmp_path: Path, scene: dict, name="scene.yml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(scene))
    return path


def read(ms: Path, *cols):
    with pt.table(str(ms), ack=False) as t:
        return [t.getcol(c) for c in cols]


# --------------------------------------------------------------------------- troposphere

def test_structure_function_matches_kolmogorov_from_1s_to_1h():
    """Ensemble D(dt) within 5% of (dt/t_c)^(5/3) at 1 s ... 1 h lags (exact generator)."""
    rng = np.random.default_rng(11)
    n_time, n_series, t_c = 7201, 2048, 10.0
    phases = tp.station_phases(n_time, 1.0, np.full(n_series, t_c), np.ones((n_series, n_time)),
                               np.zeros(n_series, int), rng)
    lags = np.array([1, 10, 100, 1000, 3600])
    measured = tp.structure_function(phases, lags)
    theory = (lags / t_c) ** (5.0 / 3.0)
    np.testing.assert_allclose(measured / theory, 1.0, atol=0.05)


def test_structure_function_scales_with_airmass_and_alternatives_fail():
    rng = np.random.default_rng(5)
    n_time, n_series = 2001, 512
    air = np.full((n_series, n_time), 2.0)
    phases = tp.station_phases(n_time, 1.0, np.full(n_series, 10.0), air,
                               np.zeros(n_series, int), rng)
    lags = np.array([1, 30, 300])
    ratio = tp.structure_function(phases, lags) / (lags / 10.0) ** (5.0 / 3.0)
    np.testing.assert_allclose(ratio, 2.0, rtol=0.05)       # coefficient x airmass
    # the random walk has the wrong exponent: it must fail the same check
    walk = tp.random_walk(n_time, 64, tp.HURST_KOLMOGOROV, rng)
    d_walk = tp.structure_function(walk, np.array([1, 300]))
    assert d_walk[1] / d_walk[0] < 0.5 * 300 ** (5.0 / 3.0)


def test_circulant_embedding_is_non_negative():
    for n in (2, 17, 1000, 43199):
        assert tp.circulant_eigenvalues(n, tp.HURST_KOLMOGOROV).min() >= 0.0


# --------------------------------------------------------------------------- end to end

@pytest.fixture(scope="module")
def noisy_pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("noisy")
    scene = small_scene(corruptions={"troposphere": False, "noise": True, "seed": 3},
                        observation={"integration": 1})
    paths = simulate(scene, out, save_truth=True)
    return scene, paths


@pytest.fixture(scope="module")
def tropo_pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("tropo")
    scene = small_scene(corruptions={"troposphere": True, "noise": False, "seed": 4})
    paths = simulate(scene, out, save_truth=True)
    return scene, paths


def test_outputs_and_columns(noisy_pair):
    scene, paths = noisy_pair
    assert [p.name for p in paths.values()] == ["sim-86.ms", "sim-230.ms", "sim-truth.npz"]
    for band in ("86", "230"):
        with pt.table(str(paths[band]), ack=False) as t:
            assert t.getcoldesc("DATA")["valueType"] == "complex"   # complex64
            data = t.getcol("DATA")
            assert data.shape[1:] == (1, 2)
            sigma, weight = t.getcol("SIGMA"), t.getcol("WEIGHT")
            np.testing.assert_allclose(weight, 1.0 / sigma ** 2, rtol=1e-6)
            time = t.getcol("TIME")
            assert np.all(np.diff(time) >= 0)
        for sub in ("ANTENNA", "FEED", "SPECTRAL_WINDOW", "POLARIZATION", "FIELD",
                    "OBSERVATION", "DATA_DESCRIPTION"):
            with pt.table(f"{paths[band]}::{sub}", ack=False) as t:
                assert t.nrows() >= 1, sub
    with pt.table(f"{paths['230']}::SPECTRAL_WINDOW", ack=False) as t:
        assert t.getcol("CHAN_FREQ")[0, 0] == 230e9 and t.getcol("NUM_CHAN")[0] == 1
    # TIME is UTC MJD seconds: the first integration centre is start + dt/2
    parsed = parse_scene(scene)
    assert read(paths["86"], "TIME")[0].min() == pytest.approx(
        parsed.start_mjd_s + parsed.integration / 2, abs=1e-6)


def test_noise_level_matches_radiometer_equation(noisy_pair):
    scene, paths = noisy_pair
    parsed = parse_scene(scene)
    obs = observe(parsed)
    for i, band in enumerate(parsed.bands):
        data, sigma, a1, a2 = read(paths[band.name], "DATA", "SIGMA", "ANTENNA1", "ANTENNA2")
        resid = (data[:, 0, :] - parsed.flux[band.name]) / sigma
        # scatter of the real and of the imaginary parts is sigma within 2%
        # (12000 rows x 2 correlations: statistical error of the std 0.5%)
        assert resid.size == 2 * 12000
        assert np.std(resid.real) == pytest.approx(1.0, rel=0.02)
        assert np.std(resid.imag) == pytest.approx(1.0, rel=0.02)
        assert abs(np.mean(resid)) < 0.03
        # and sigma itself is the radiometer equation, recomputed here for row 0
        r = 0
        p, q, t = a1[r], a2[r], obs.time_index[r]
        sefd = []
        for s in (p, q):
            st = parsed.stations[s]
            sb = st.bands[band.name]
            x = 1.0 / np.sin(obs.elevation[s, t])
            tsys = (sb.t_rx + sb.t_atm * (1 - np.exp(-sb.tau * x))) * np.exp(sb.tau * x)
            area = sb.aperture_efficiency * np.pi * st.diameter ** 2 / 4
            sefd.append(2 * 1.380649e-23 * tsys / area * 1e26)
        expected = np.sqrt(sefd[0] * sefd[1] / (2 * band.bandwidth_hz * parsed.integration)) / 0.88
        assert sigma[r, 0] == pytest.approx(expected, rel=1e-5)


def test_sefd_of_a_known_case():
    # 12 m dish, 50% efficiency, Tsys 100 K: SEFD = 2 k T / A = 4883 Jy
    t_sys = noise_mod.system_temperature(100.0, 0.0, 0.0, np.array([1.0]))
    assert noise_mod.sefd(t_sys, 12.0, 0.5)[0] == pytest.approx(4883.2, rel=1e-4)
    assert noise_mod.baseline_sigma(1000.0, 1000.0, 2e9, 1.0)[()] == pytest.approx(
        np.sqrt(1e6 / 4e9) / 0.88)


def test_frequency_scaling_between_bands_is_exactly_R(tropo_pair):
    scene, paths = tropo_pair
    truth = np.load(paths["truth"])
    ratio = 230.0 / 86.0
    np.testing.assert_allclose(truth["phase_230"], ratio * truth["phase_86"], rtol=1e-12, atol=1e-12)
    assert list(truth["stations"]) == ["AP", "PV", "GL", "PB", "KP"]
    # the visibilities carry those phases: V_pq = S exp(i (phi_p - phi_q)), both bands
    t_index = {t: i for i, t in enumerate(truth["time"])}
    for band, flux in (("86", 1.1), ("230", 1.0)):
        data, a1, a2, time = read(paths[band], "DATA", "ANTENNA1", "ANTENNA2", "TIME")
        it = np.array([t_index[t] for t in time])
        phase = truth[f"phase_{band}"]
        expected = flux * np.exp(1j * (phase[a1, it] - phase[a2, it]))
        np.testing.assert_allclose(data[:, 0, 0], expected, atol=2e-6)
        np.testing.assert_allclose(data[:, 0, 1], expected, atol=2e-6)
    # the troposphere is really there: phases move by radians over 20 min at 230 GHz
    assert np.ptp(truth["phase_230"]) > 2 * np.pi


def test_rows_only_while_both_stations_are_up(tmp_path):
    scene = small_scene(observation={"duration": 43200, "integration": 60,
                                     "start": "2023-04-10T00:00:00"},
                        corruptions={"troposphere": False, "noise": False})
    paths = simulate(scene, tmp_path, save_truth=True)
    truth = np.load(paths["truth"])
    a1, a2, time = read(paths["86"], "ANTENNA1", "ANTENNA2", "TIME")
    t_index = {t: i for i, t in enumerate(truth["time"])}
    it = np.array([t_index[t] for t in time])
    limit = np.radians(10.0)
    el = truth["elevation"]
    assert np.all(el[a1, it] > limit) and np.all(el[a2, it] > limit)
    # and every (time, baseline) with both up is present
    up = el > limit
    expected = sum(int(np.sum(up[p] & up[q])) for p in range(5) for q in range(p + 1, 5))
    assert time.size == expected < 10 * truth["time"].size


def test_scan_pattern(tmp_path):
    scene = small_scene(observation={"duration": 1200, "integration": 10, "scan_length": 300,
                                     "scan_gap": 100},
                        corruptions={"troposphere": False, "noise": False})
    paths = simulate(scene, tmp_path)
    time, scan = read(paths["86"], "TIME", "SCAN_NUMBER")
    start = parse_scene(scene).start_mjd_s
    offset = np.mod(time - start, 400.0)
    assert offset.max() < 300 and set(scan) == {1, 2, 3}


def test_same_seed_same_data_different_seed_different_data(tmp_path):
    scene = small_scene(observation={"duration": 300})
    a = simulate(scene, tmp_path / "a", seed=9)
    b = simulate(scene, tmp_path / "b", seed=9)
    c = simulate(scene, tmp_path / "c", seed=10)
    for band in ("86", "230"):
        da, db, dc = (read(p[band], "DATA")[0] for p in (a, b, c))
        assert np.array_equal(da, db)
        assert not np.allclose(da, dc)


def test_overrides_and_paired_antenna_names(tmp_path):
    scene = small_scene()
    scene["stations"] = ["AP", "PV", {"code": "SM", "bands": {"86": {"name": "JC"}}}]
    scene["observation"]["start"] = "2023-04-10T07:00:00"   # AP and SM both up
    paths = simulate(scene, tmp_path, stations="AP,SM", duration=600, integration=5,
                     no_troposphere=True, no_noise=True, correlations="RR,RL,LR,LL")
    names86 = read(Path(f"{paths['86']}::ANTENNA"), "NAME")[0]
    names230 = read(Path(f"{paths['230']}::ANTENNA"), "NAME")[0]
    assert list(names86) == ["AP", "JC"] and list(names230) == ["AP", "SM"]
    data, time = read(paths["230"], "DATA", "TIME")
    assert data.shape[2] == 4 and np.ptp(time) <= 600
    np.testing.assert_allclose(data[:, 0, [0, 3]], 1.0, atol=1e-6)   # RR, LL = I
    assert np.all(data[:, 0, [1, 2]] == 0)                            # noise off: cross hands 0


# --------------------------------------------------------------------------- bad input

BAD_SCENES = {
    "unknown station": (lambda s: s.update(stations=["AP", "XX"]), "stations[1].code"),
    "missing field": (lambda s: s["source"].pop("ra"), "source.ra"),
    "negative flux": (lambda s: s["source"]["flux"].update({"230": -1.0}), "source.flux.230"),
    "negative temperature": (lambda s: s.update(stations=["AP", {"code": "PV", "bands": {
        "230": {"t_rx": -5}}}]), "stations[1].bands.230.t_rx"),
    "integration longer than duration": (
        lambda s: s["observation"].update(integration=5000), "observation.integration"),
    "zero bandwidth": (lambda s: s["bands"][1].update(bandwidth_ghz=0), "bands[1].bandwidth_ghz"),
    "never above the limit": (lambda s: s["source"].update(dec="-89d00m00s"), "elevation limits"),
    "missing section": (lambda s: s.pop("observation"), "observation"),
    "typo in a field": (lambda s: s["observation"].update(integraton=1), "observation.integraton"),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENES))
def test_bad_scene_names_the_field_and_writes_nothing(tmp_path, case):
    mutate, field = BAD_SCENES[case]
    scene = small_scene()
    mutate(scene)
    path = write_scene(tmp_path, scene)
    out = tmp_path / "out"
    with pytest.raises(SceneError, match=field.replace("[", r"\[").replace("]", r"\]")):
        simulate(path, out)
    assert not out.exists() or not any(out.iterdir())


def test_cli_bad_input_exits_non_zero_with_message(tmp_path):
    scene = small_scene()
    scene["bands"][0]["bandwidth_ghz"] = 0
    path = write_scene(tmp_path, scene)
    proc = subprocess.run(HITOPS + ["simulate", str(path), "--outdir", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "bands[0].bandwidth_ghz" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_existing_output_needs_overwrite(tmp_path):
    scene = small_scene(observation={"duration": 120})
    simulate(scene, tmp_path)
    before = read(tmp_path / "sim-86.ms", "DATA")[0]
    with pytest.raises(OutputExistsError, match="sim-86.ms"):
        simulate(scene, tmp_path, seed=99)
    assert np.array_equal(read(tmp_path / "sim-86.ms", "DATA")[0], before)
    simulate(scene, tmp_path, seed=99, overwrite=True)
    assert not np.array_equal(read(tmp_path / "sim-86.ms", "DATA")[0], before)
    # each set with its flags as simulated, kept as a CASA flag version
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "sim-230.ms", "sim-230.ms.flagversions", "sim-86.ms", "sim-86.ms.flagversions"]


def test_cli_runs_packaged_scene_with_overrides(tmp_path):
    proc = subprocess.run(HITOPS + ["simulate", "demo", "--outdir", str(tmp_path), "--prefix", "d",
                                    "--duration", "240", "--seed", "3", "--save-truth",
                                    "--stations", "AP,PV,PB"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "d-230.ms", "d-230.ms.flagversions", "d-86.ms", "d-86.ms.flagversions", "d-truth.npz"]
    truth = np.load(tmp_path / "d-truth.npz")
    assert list(truth["stations"]) == ["AP", "PV", "PB"]


def test_packaged_paper_scene_matches_the_paper():
    scene = parse_scene("paper")
    assert [s.code for s in scene.stations] == ["AP", "SM", "PV", "GL", "PB", "KP", "KC", "KY"]
    assert scene.flux == {"86": 1.1, "230": 1.0}
    assert (scene.duration, scene.integration) == (43200, 1)
    assert [b.freq_hz for b in scene.bands] == [86e9, 230e9]
    assert all(b.bandwidth_hz == 2e9 for b in scene.bands)
    trx = {s.code: (s.bands["86"].t_rx, s.bands["230"].t_rx, s.diameter) for s in scene.stations}
    assert trx["AP"] == (40, 85, 12) and trx["PB"] == (50, 80, 50) and trx["PV"] == (30, 60, 30)


def test_gaussian_component_visibilities(tmp_path):
    """A centred circular Gaussian: V = F exp(-pi^2 theta^2 |uv|^2 / (4 ln 2)), uv in wavelengths."""
    scene = small_scene(corruptions={"troposphere": False, "noise": False},
                        observation={"duration": 600, "integration": 10})
    scene["source"]["flux"] = {"86": 0.0, "230": 0.0}
    scene["source"]["components"] = [{"flux": {"86": 2.0, "230": 1.5}, "fwhm_major": 20.0}]
    paths = simulate(scene, tmp_path)
    theta = np.radians(20.0 / 3600e6)
    amplitudes = {}
    for band, freq, flux in (("86", 86e9, 2.0), ("230", 230e9, 1.5)):
        data, uvw = read(paths[band], "DATA", "UVW")
        rho = np.hypot(uvw[:, 0], uvw[:, 1]) * freq / 299792458.0
        expected = flux * np.exp(-(np.pi * theta * rho) ** 2 / (4 * np.log(2)))
        np.testing.assert_allclose(data[:, 0, 0], expected, atol=1e-6)
        amplitudes[band] = np.abs(data[:, 0, 0]) / flux
    # a 20 uas source is resolved on these baselines at 230 GHz, much less at 86 GHz
    assert amplitudes["230"].min() < 0.3 < amplitudes["86"].min()
