"""The verdict's closure check speaks only of structure that is there.

Both pairs are built from physics, not from the code under test: four EHT
stations (ITRF positions from hitops/scenes/stations.yml), (u, v) from the
Earth's rotation (Thompson, Moran & Swenson, eq. 4.1), a source of point
components whose visibility is sum_k F_k exp(-2 pi i (u l_k + v m_k)), station
phases of a non-dispersive troposphere (R times larger at the target band).

* a point source at the phase centre without noise: every closure phase is zero
  up to float32 rounding, its standard error is zero too, so the old test
  (3 standard errors) alone called it structure; the floor in degrees must not;
* a resolved source (two components 30 uas apart) with thermal noise: its
  closure phases at 86 GHz are tens of degrees, the warning must come.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate.verdict import CLOSURE_FLOOR_DEG, CLOSURE_SIGNIFICANCE
from hitops.geometry import earth_rotation_angle
from hitops.io.ms_create import ArrayLayout, Band, Field, create_ms

#: ITRF metres (hitops/scenes/stations.yml)
STATIONS = {"AP": (2225039.5297, -5441197.6292, -2479303.3597),
            "SM": (-5464555.493, -2492927.989, 2150797.176),
            "PV": (5088967.74544, -301681.18586, 3825012.20561),
            "KP": (-1995953.2507, -5037384.5859, 3357045.5186)}
RA, DEC = 3.2766, 0.2164          # M87 (rad)
UAS = np.radians(1e-6 / 3600.0)
C = 299_792_458.0
WARNING = "closure phases are not consistent with zero"


def station_uvw_m(positions: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(n_time, n_ant, 3) station (u, v, w) in metres toward (RA, DEC): TMS eq. 4.1 with the
    Greenwich hour angle (baseline vectors are differences of these)."""
    hour = earth_rotation_angle(times)[:, None] - RA
    x, y, z = positions[:, 0][None], positions[:, 1][None], positions[:, 2][None]
    u = np.sin(hour) * x + np.cos(hour) * y
    v = -np.sin(DEC) * np.cos(hour) * x + np.sin(DEC) * np.sin(hour) * y + np.cos(DEC) * z
    w = np.cos(DEC) * np.cos(hour) * x - np.cos(DEC) * np.sin(hour) * y + np.sin(DEC) * z
    return np.stack([u, v, w], axis=-1)


def write_pair(directory, components, sigma: float, seed: int = 4, n_time: int = 900):
    """ref.ms (86 GHz) and target.ms (230 GHz) of ``components`` [(flux, l, m) rad], rows in
    time order, RR and LL alike; thermal noise ``sigma`` per real/imaginary part."""
    rng = np.random.default_rng(seed)
    names = list(STATIONS)
    positions = np.array([STATIONS[n] for n in names])
    n_ant = len(names)
    times = 5.1e9 + np.arange(n_time, dtype=np.float64)
    uvw_ant = station_uvw_m(positions, times)
    a1, a2 = np.triu_indices(n_ant, 1)
    # rows in time order: every baseline at each time
    ant1, ant2 = np.tile(a1, n_time), np.tile(a2, n_time)
    t_idx = np.repeat(np.arange(n_time), a1.size)
    uvw = uvw_ant[t_idx, ant1] - uvw_ant[t_idx, ant2]
    # troposphere: a random walk per station at 86 GHz (radians), non-dispersive
    walk = np.cumsum(rng.normal(0.0, 0.05, (n_time, n_ant)), axis=0)
    paths = {}
    for freq, name in ((86e9, "ref.ms"), (230e9, "target.ms")):
        wavelengths = uvw[:, :2] * freq / C
        source = sum(flux * np.exp(-2j * np.pi * (wavelengths[:, 0] * l + wavelengths[:, 1] * m))
                     for flux, l, m in components)
        station = np.exp(1j * (freq / 86e9) * (walk[t_idx, ant1] - walk[t_idx, ant2]))
        vis = np.repeat((source * station)[:, None], 2, axis=1)
        if sigma:
            vis = vis + rng.normal(0, sigma, vis.shape) + 1j * rng.normal(0, sigma, vis.shape)
        layout = ArrayLayout(names, names, positions, np.full(n_ant, 12.0))
        paths[name] = create_ms(directory / name, layout, Band(freq, 2e9, ("RR", "LL")),
                                Field("M87", RA, DEC),
                                {"TIME": times[t_idx], "ANTENNA1": ant1, "ANTENNA2": ant2,
                                 "UVW": uvw, "DATA": vis, "INTERVAL": np.ones(t_idx.size)})
    return paths["ref.ms"], paths["target.ms"]


def run(tmp_path, caplog, components, sigma):
    ref, tgt = write_pair(tmp_path, components, sigma)
    with caplog.at_level(logging.INFO, logger="hitops"):
        report = calibrate_flat(str(ref), str(tgt), method="pwc")
    return report["verdict"]["reference_closure"]


def test_noise_free_point_source_no_closure_warning(tmp_path, caplog):
    closure = run(tmp_path, caplog, [(1.0, 0.0, 0.0)], sigma=0.0)
    assert closure["median_abs_mean_closure_deg"] < 1e-3     # rounding only
    # the standard-error test alone fires on rounding (zero noise, zero standard error):
    # the floor in degrees is what keeps it quiet
    assert closure["median_significance"] > CLOSURE_SIGNIFICANCE
    assert closure["consistent_with_zero"]
    assert WARNING not in caplog.text


def test_resolved_source_closure_warning(tmp_path, caplog):
    closure = run(tmp_path, caplog, [(1.0, 0.0, 0.0), (0.6, 30 * UAS, 20 * UAS)], sigma=0.05)
    assert closure["median_abs_mean_closure_deg"] > 5 * CLOSURE_FLOOR_DEG
    assert closure["median_significance"] > CLOSURE_SIGNIFICANCE
    assert not closure["consistent_with_zero"]
    assert WARNING in caplog.text and "--tracker antenna" in caplog.text


def test_resolved_source_no_warning_with_the_antenna_tracker(tmp_path, caplog):
    """The antenna tracker keeps the target's closure phases: nothing to warn of."""
    ref, tgt = write_pair(tmp_path, [(1.0, 0.0, 0.0), (0.6, 30 * UAS, 20 * UAS)], sigma=0.05)
    with caplog.at_level(logging.INFO, logger="hitops"):
        report = calibrate_flat(str(ref), str(tgt), method="pwc", tracker="antenna")
    assert not report["verdict"]["reference_closure"]["consistent_with_zero"]
    assert WARNING not in caplog.text


@pytest.mark.parametrize("sigma", [0.0, 0.05])
def test_point_source_closures_consistent(tmp_path, caplog, sigma):
    """With or without noise, a point source's closures count as zero."""
    closure = run(tmp_path, caplog, [(1.0, 0.0, 0.0)], sigma=sigma)
    assert closure["consistent_with_zero"]
