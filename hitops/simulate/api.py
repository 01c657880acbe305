"""``simulate(scene, outdir, ...)``: multi-band Measurement Sets from a scene.

Steps: time grid -> geometry (casacore-anchored UVW, elevations) -> rows
while both stations are above their limits -> one troposphere realisation
(an excess path per station) -> per band, window and channel: model x station
phases + thermal noise (hitops.simulate.bands) -> one Measurement Set per band
(hitops.simulate.ms_windows) (+ truth .npz).  All outputs
are written under temporary names and renamed at the end, so a failure
leaves nothing half-written.
"""

from __future__ import annotations

import logging
import shutil
import time as _time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from ..errors import OutputExistsError, SceneError
from ..io.flag_versions import keep_original
from ..io.ms_create import ArrayLayout, Field
from .. import radiometer
from . import geometry, troposphere
from .bands import band_blocks, band_phase, instrumental_series, station_opacity
from .ms_windows import write_band_ms
from .msv4_out import check_format, convert_bands, store_path
from .scene import Scene, apply_overrides, parse_scene
from .sources import C_LIGHT

log = logging.getLogger("hitops.simulate")



@dataclass
class Observation:
    """Everything the bands share: time grid, rows, geometry, troposphere."""

    times: np.ndarray          # (n_time,) UTC MJD seconds, integration centres
    scan: np.ndarray           # (n_time,) scan number
    elevation: np.ndarray      # (n_station, n_time) rad
    station_uvw: np.ndarray    # (n_station, n_time, 3) m
    time_index: np.ndarray     # (n_row,) index into times
    ant1: np.ndarray           # (n_row,) int32
    ant2: np.ndarray           # (n_row,) int32
    uvw: np.ndarray            # (n_row, 3) m, uvw[ant1] - uvw[ant2] (see geometry.py)
    # (n_station, n_time) troposphere phase at the coherence frequency nu0: the excess
    # path is L = phase_ref c / (2 pi nu0), and channel nu sees phase_ref nu / nu0
    phase_ref: np.ndarray
    coherence_time: Optional[np.ndarray] = None   # (n_station, n_time) zenith t_c used (s), at nu0
    weather: Optional[List] = None                # per station: StationWeather or None
    # (n_time,) int32 FIELD_ID of each integration (0 target, 1 calibrator); None: one field
    field_id: Optional[np.ndarray] = None


def output_paths(outdir: str | Path, prefix: str, scene: Scene, save_truth: bool) -> Dict[str, Path]:
    outdir = Path(outdir)
    paths = {band.name: outdir / f"{prefix}-{band.name}.ms" for band in scene.bands}
    if save_truth:
        paths["truth"] = outdir / f"{prefix}-truth.npz"
    return paths


def observe(scene: Scene) -> Observation:
    """Rows, geometry and troposphere of a scene (band independent)."""
    field_id = None
    if scene.calibrator is None:
        times, scan, on_source = geometry.time_grid(scene.start_mjd_s, scene.duration,
                                                    scene.integration, scene.scan_length,
                                                    scene.scan_gap)
    else:
        times, scan, on_source, field_id = geometry.alternating_grid(
            scene.start_mjd_s, scene.duration, scene.integration, scene.scan_length,
            scene.calibrator.scan_length, scene.scan_gap)
    positions = np.array([s.itrf for s in scene.stations])
    matrices = geometry.uvw_matrices(times, scene.ra, scene.dec, positions[0])
    if field_id is not None:
        # the calibrator's integrations look at its own phase centre: its own (u, v, w)
        # and elevations (and airmass for the noise and the turbulence below)
        on_cal = field_id == 1
        matrices[on_cal] = geometry.uvw_matrices(times[on_cal], scene.calibrator.ra,
                                                 scene.calibrator.dec, positions[0])
    station_uvw = geometry.station_uvw(matrices, positions)
    elevation = geometry.station_elevation(matrices, positions)
    limits = np.radians([s.elevation_limit for s in scene.stations])
    up = elevation > limits[:, None]

    n_station = len(scene.stations)
    bl_ant1, bl_ant2 = np.triu_indices(n_station, k=1)
    visible = (up[bl_ant1] & up[bl_ant2]) & on_source[None, :]      # (n_bl, n_time)
    time_index, bl_index = np.nonzero(visible.T)                     # time-major row order
    if time_index.size == 0:
        raise SceneError(
            f"scene {scene.source_file}: source {scene.source_name} is never above the "
            "elevation limits (stations[*].elevation_limit) of two stations at the same time "
            "during the observation; change observation.start/duration, the stations or "
            "their elevation limits")
    ant1 = bl_ant1[bl_index].astype(np.int32)
    ant2 = bl_ant2[bl_index].astype(np.int32)
    uvw = station_uvw[ant1, time_index] - station_uvw[ant2, time_index]

    n_time = times.size
    weather = station_weathers(scene, times)
    t_c = coherence_times(scene, weather, n_time)
    if scene.troposphere:
        rng = np.random.default_rng(np.random.SeedSequence([scene.seed, 1]))
        # airmass of the turbulent layer, floored at the station's elevation limit
        # (phases below the limit are never observed; they only carry the walk on)
        # and at the scene's airmass floor
        floor_el = np.maximum(elevation, limits[:, None])
        if scene.airmass_elevation_floor is not None:
            floor_el = np.maximum(floor_el, np.radians(scene.airmass_elevation_floor))
        air = radiometer.airmass(floor_el)
        first_up = np.where(up.any(axis=1), up.argmax(axis=1), 0)
        phase_ref = troposphere.station_phases(n_time, scene.integration, t_c, air, first_up, rng)
        phase_ref = _own_paths(scene, field_id, phase_ref, t_c, air, first_up)
    else:
        phase_ref = np.zeros((n_station, n_time))
    return Observation(times, scan, elevation, station_uvw, time_index, ant1, ant2, uvw, phase_ref,
                       t_c, weather, field_id)


def _own_paths(scene: Scene, field_id, shared: np.ndarray, t_c, air, first_up) -> np.ndarray:
    """Each field's line of sight its own path beside the shared one (issue 38): a screen
    of the same statistics per station and field, ``calibrator.own_troposphere`` times
    the shared part, added on that field's integrations.  Nothing is drawn without it
    (scenes without the key are written as before, byte for byte)."""
    own = 0.0 if scene.calibrator is None else scene.calibrator.own_troposphere
    if not own:
        return shared
    rng = np.random.default_rng(np.random.SeedSequence([scene.seed, 2]))
    n_time = shared.shape[1]
    per_field = [troposphere.station_phases(n_time, scene.integration, t_c, air, first_up, rng)
                 for _ in range(2)]
    return shared + own * np.where(field_id[None, :] == 1, per_field[1], per_field[0])


def station_weathers(scene: Scene, times: np.ndarray) -> List:
    """Each station's MERRA-2 weather on the time grid (None where the scene gives none).

    Raises :class:`hitops.weather.WeatherError` (before anything is written) when
    the tables cannot give a station's date, month or band.
    """
    from ..weather import station_weather
    from ..weather.tables import MJD_EPOCH

    out = []
    start_date = (MJD_EPOCH.toordinal() + int(times.min() // 86400)) if times.size else None
    for station in scene.stations:
        spec = station.weather
        if spec is None:
            out.append(None)
            continue
        date = spec.date
        if date is None and spec.month is None:
            import datetime as _dt

            date = _dt.date.fromordinal(start_date).isoformat()
        bands = [(b.name, b.freq_hz) for b in scene.bands if b.name in spec.bands]
        w = station_weather(station.code, bands, times, site=spec.site, date=date,
                            year=spec.year, month=spec.month, statistic=spec.statistic,
                            fallback=spec.fallback)
        out.append(w)
        values = ", ".join(f"tau{b} {np.median(w.tau[b]):.3f} Tb{b} {np.median(w.tb[b]):.1f} K"
                           for b in w.tau)
        log.info("weather %s: %s; median %s; wind %.1f m/s%s", station.code, w.description,
                 values or "(opacities given in the scene)", float(np.median(w.wind)),
                 "" if spec.coherence else " (coherence time given in the scene)")
    return out


def coherence_times(scene: Scene, weather: List, n_time: int) -> np.ndarray:
    """Zenith t_c (s) at the coherence frequency per station and time (n_station, n_time).

    Stations with weather-driven coherence: t_c(230 GHz) = r0 / wind, scaled to
    the coherence frequency as nu^(-6/5); the others keep their scene value.
    """
    from ..weather.tables import MIN_WIND

    t_c = np.empty((len(scene.stations), n_time))
    for i, station in enumerate(scene.stations):
        w, spec = weather[i], station.weather
        if w is not None and spec.coherence:
            r0 = spec.r0 * (scene.coherence_freq_hz / 230e9) ** (-6.0 / 5.0)
            t_c[i] = r0 / np.maximum(w.wind, MIN_WIND)
        else:
            t_c[i] = station.coherence_time
    return t_c * scene.coherence_scale


def _write_band(scene: Scene, band_index: int, obs: Observation, path: Path) -> Path:
    band = scene.bands[band_index]
    layout = ArrayLayout(
        names=[s.bands[band.name].antenna_name for s in scene.stations],
        stations=[s.name for s in scene.stations],
        positions=np.array([s.itrf for s in scene.stations]),
        diameters=np.array([s.diameter for s in scene.stations]))
    t0 = _time.perf_counter()
    rows = obs.ant1.size * band.n_window
    time_range = (float(obs.times[obs.time_index].min()), float(obs.times[obs.time_index].max()))
    write_band_ms(path, layout, band, scene.correlations,
                  Field(scene.source_name, scene.ra, scene.dec),
                  band_blocks(scene, band_index, obs), rows, time_range, scene.telescope,
                  calibrator=(None if scene.calibrator is None else
                              Field(scene.calibrator.name, scene.calibrator.ra,
                                    scene.calibrator.dec)))
    log.info("band %s: %d rows x %d window(s) x %d channel(s), computed and written in %.1f s"
             " -> %s", band.name, obs.ant1.size, band.n_window, band.n_chan,
             _time.perf_counter() - t0, path)
    return path


def write_truth(scene: Scene, obs: Observation, path: Path) -> None:
    """Per-station unwrapped troposphere phases per band, with names and times.

    ``path_m`` is each station's excess path L(t) (m): the phase of channel nu is
    2 pi nu L / c (``phase_BAND`` is that at the band's nominal frequency);
    ``chan_freq_BAND`` (n_window, n_chan) the channel frequencies; a band with
    instrumental terms adds ``inst_phase_BAND`` (rad, at the band's nominal
    frequency) and ``inst_delay_BAND`` (s), each (n_station, n_time).  A scene with a
    calibrator adds ``field_id`` (n_time,), the FIELD_ID of each integration, and
    ``fields`` (the FIELD names: target, calibrator).
    """
    arrays = {
        "stations": np.array([s.code for s in scene.stations]),
        "time": obs.times,
        "bands": np.array([b.name for b in scene.bands]),
        "freq_hz": np.array([b.freq_hz for b in scene.bands]),
        "elevation": obs.elevation,
        "coherence_time": (np.median(obs.coherence_time, axis=1) if obs.coherence_time is not None
                           else np.array([s.coherence_time * scene.coherence_scale
                                          for s in scene.stations])),
        "coherence_freq_hz": np.float64(scene.coherence_freq_hz),
        "convention": np.array("V_pq = V_model * exp(i*(phase[p] - phase[q])), "
                               "p = ANTENNA1, q = ANTENNA2; radians, unwrapped"),
    }
    # the weather actually used, per station and time (float32: values, not bit patterns)
    n_time = obs.times.size
    if obs.coherence_time is not None:
        arrays["coherence_time_series"] = obs.coherence_time.astype(np.float32)
    arrays["weather_source"] = np.array([w.description if w is not None else "scene values"
                                         for w in (obs.weather or [None] * len(scene.stations))])
    arrays["wind"] = np.array([w.wind if w is not None else np.full(n_time, np.nan)
                               for w in (obs.weather or [None] * len(scene.stations))],
                              dtype=np.float32)
    for band in scene.bands:
        taus, tskies = [], []
        for i in range(len(scene.stations)):
            tau, t_atm = station_opacity(scene, obs, i, band.name)
            tau = np.broadcast_to(np.asarray(tau, dtype=np.float64), (n_time,))
            taus.append(tau)
            tskies.append(np.asarray(t_atm) * -np.expm1(-tau))
        arrays[f"tau_{band.name}"] = np.array(taus, dtype=np.float32)
        arrays[f"tsky_{band.name}"] = np.array(tskies, dtype=np.float32)
    for i, band in enumerate(scene.bands):
        arrays[f"phase_{band.name}"] = band_phase(scene, i, obs)
        arrays[f"antenna_names_{band.name}"] = np.array(
            [s.bands[band.name].antenna_name for s in scene.stations])
        arrays[f"chan_freq_{band.name}"] = band.chan_freq()
        inst = instrumental_series(scene, i, obs)
        if inst is not None:
            arrays[f"inst_phase_{band.name}"], arrays[f"inst_delay_{band.name}"] = inst
    if obs.field_id is not None:
        arrays["field_id"] = obs.field_id
        arrays["fields"] = np.array([scene.source_name, scene.calibrator.name])
    arrays["path_m"] = obs.phase_ref * (C_LIGHT / (2.0 * np.pi * scene.coherence_freq_hz))
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


def simulate(scene, outdir, prefix: str = "sim", seed: Optional[int] = None,
             save_truth: bool = False, overwrite: bool = False, duration=None,
             integration=None, coherence_scale=None, no_noise: bool = False,
             no_troposphere: bool = False, stations=None, start=None, scan_length=None,
             scan_gap=None, correlations=None, threads: int = 1,
             format: str = "ms") -> Dict[str, Path]:
    """Simulate a scene; return {band name: MS path, ['truth': npz path]}.

    ``format="msv4"`` also converts each band's Measurement Set into an MSv4
    processing set beside it (hitops/simulate/msv4_out.py), returned as
    ``'<band>.ps.zarr'``.

    ``scene`` is a :class:`Scene`, a YAML path, a packaged scene name
    ('paper', 'demo', 'triband', 'ngeht', 'phaseref') or a mapping; keyword overrides replace the scene's
    values (see :func:`hitops.simulate.scene.apply_overrides`).
    """
    scene = scene if isinstance(scene, Scene) else parse_scene(scene)
    scene = apply_overrides(scene, duration=duration, integration=integration, seed=seed,
                            coherence_scale=coherence_scale, no_noise=no_noise,
                            no_troposphere=no_troposphere, stations=stations, start=start,
                            scan_length=scan_length, scan_gap=scan_gap,
                            correlations=correlations)
    if not prefix or "/" in prefix:
        raise SceneError(f"prefix {prefix!r} must be a plain file-name prefix like 'sim'")
    check_format(format)
    paths = output_paths(outdir, prefix, scene, save_truth)
    stores = [store_path(paths[b.name]) for b in scene.bands] if format == "msv4" else []
    existing = [str(p) for p in [*paths.values(), *stores] if p.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} exist(s); pass --overwrite "
                                "(overwrite=True) to replace, or choose another --outdir/--prefix")

    t0 = _time.perf_counter()
    obs = observe(scene)
    log.info("scene %s: %d stations, %d times, %d rows per band (%.1f s)", scene.name,
             len(scene.stations), obs.times.size, obs.ant1.size, _time.perf_counter() - t0)

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    staging = {key: p.with_name(f".{p.name}.writing") for key, p in paths.items()}
    try:
        for tmp in staging.values():
            _remove(tmp)
        # threads > 1 overlaps the bands (numpy/numba release the GIL); casacore
        # does not promise thread safety, so the default writes one band at a time
        with ThreadPoolExecutor(max_workers=max(1, min(threads, len(scene.bands)))) as pool:
            futures = [pool.submit(_write_band, scene, i, obs, staging[b.name])
                       for i, b in enumerate(scene.bands)]
            for fut in futures:
                fut.result()
        if save_truth:
            write_truth(scene, obs, staging["truth"])
        for key, final in paths.items():
            _remove(final)
            staging[key].rename(final)
            if final.suffix == ".ms":
                # the flags as simulated, as a CASA flag version: every recipe step that
                # flags starts from it, so a rerun is a fresh run (hitops/io/flag_versions.py)
                keep_original(final, "simulated")
    except BaseException:
        for tmp in staging.values():
            _remove(tmp)
        raise
    if stores:
        converted = convert_bands([paths[b.name] for b in scene.bands], len(scene.stations))
        paths.update({f"{b.name}.ps.zarr": converted[paths[b.name]] for b in scene.bands})
    log.info("simulate: wrote %s in %.1f s", ", ".join(str(p) for p in paths.values()),
             _time.perf_counter() - t0)
    return paths


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
