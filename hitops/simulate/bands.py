"""One band's main-table columns: model x station phases + thermal noise, per window.

A band holds one or more spectral windows of n_chan channels each
(:class:`hitops.simulate.scene_parts.BandSpec`).  Per window and channel k:

* troposphere: phase 2 pi nu_k L_p(t) / c of each station's excess path, i.e.
  (nu_k / nu_0) x the phase at the coherence frequency nu_0;
* instrumental (optional, per station and band): phase + 2 pi (nu_k - nu_band) x delay,
  both constant or drifting linearly;
* thermal noise from the radiometer equation with the channel width as bandwidth.

Rows of a band with several windows are ordered by (time, window, baseline), as a
correlator writes them, with DATA_DESC_ID = window index.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np

from .. import radiometer
from .kernels import corrupt_channels
from .sources import model_visibilities


def station_opacity(scene, obs, index: int, band_name: str):
    """(zenith opacity, T_atm) of a station in a band: arrays over time from the weather
    (T_atm = Tb / (1 - exp(-tau)), so the zenith sky temperature is the tabulated Tb),
    else the scene's scalars."""
    w = obs.weather[index] if obs.weather else None
    if w is not None and band_name in w.tau:
        from ..weather import effective_temperature

        return w.tau[band_name], effective_temperature(w.tau[band_name], w.tb[band_name])
    sb = scene.stations[index].bands[band_name]
    return sb.tau, sb.t_atm


def band_sigma(scene, band_index: int, obs) -> np.ndarray:
    """Per-row noise rms (Jy) of each of the real and imaginary parts of one channel."""
    band = scene.bands[band_index]
    elevation = obs.elevation
    if scene.airmass_elevation_floor is not None:
        elevation = np.maximum(elevation, np.radians(scene.airmass_elevation_floor))
    air = radiometer.airmass(elevation)
    sefd = np.empty_like(obs.elevation)
    for i, station in enumerate(scene.stations):
        sb = station.bands[band.name]
        tau, t_atm = station_opacity(scene, obs, i, band.name)
        t_sys = radiometer.system_temperature(sb.t_rx, t_atm, tau, air[i])
        sefd[i] = radiometer.sefd(t_sys, station.diameter, sb.aperture_efficiency)
    return radiometer.baseline_sigma(sefd[obs.ant1, obs.time_index],
                                     sefd[obs.ant2, obs.time_index],
                                     band.channel_width_hz, scene.integration,
                                     scene.quantisation_efficiency)


def band_phase(scene, band_index: int, obs) -> np.ndarray:
    """Tropospheric station phases at the band's nominal frequency: (nu / nu0) x phase at nu0."""
    return obs.phase_ref * (scene.bands[band_index].freq_hz / scene.coherence_freq_hz)


def instrumental_series(scene, band_index: int, obs) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(phase (rad), delay (s)), each (n_station, n_time), of the band's instrumental terms;
    None when no station has any."""
    band = scene.bands[band_index]
    terms = [s.bands[band.name].instrumental for s in scene.stations]
    if all(t is None for t in terms):
        return None
    elapsed = obs.times - scene.start_mjd_s
    phase = np.zeros((len(terms), elapsed.size))
    delay = np.zeros_like(phase)
    for i, term in enumerate(terms):
        if term is not None:
            phase[i], delay[i] = term.series(elapsed)
    return phase, delay


def window_data(scene, band_index: int, window: int, obs, sigma: np.ndarray,
                inst: Optional[Tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """DATA (n_row, n_chan, n_corr) complex64 of one spectral window of a band
    (``inst``: :func:`instrumental_series` of the band)."""
    band = scene.bands[band_index]
    chan_freq = band.chan_freq()[window]
    n_corr = len(scene.correlations)
    parallel = np.array([c[0] == c[1] for c in scene.correlations])
    if scene.noise:
        # window 0 draws exactly the stream of the single-channel simulator
        key = [scene.seed, 2, band_index] + ([window] if window else [])
        rng = np.random.default_rng(np.random.SeedSequence(key))
        draws = rng.standard_normal((obs.ant1.size, chan_freq.size, n_corr, 2), dtype=np.float32)
    else:
        draws = np.zeros((0, chan_freq.size, n_corr, 2), np.float32)
    if inst is None:
        inst = (np.zeros((0, 0)), np.zeros((0, 0)))
    return corrupt_channels(model_visibilities(scene, band.name, obs.uvw, chan_freq), obs.ant1,
                            obs.ant2, obs.time_index, obs.phase_ref,
                            chan_freq / scene.coherence_freq_hz, inst[0], inst[1],
                            chan_freq - band.freq_hz, parallel, draws, sigma)


def band_columns(scene, band_index: int, obs) -> Dict[str, np.ndarray]:
    """Main-table columns of one band's Measurement Set (all its windows)."""
    band = scene.bands[band_index]
    n_corr = len(scene.correlations)
    sigma = band_sigma(scene, band_index, obs)
    per_row = {
        "TIME": obs.times[obs.time_index],
        "ANTENNA1": obs.ant1,
        "ANTENNA2": obs.ant2,
        "UVW": obs.uvw,
        "SCAN_NUMBER": obs.scan[obs.time_index],
        "INTERVAL": np.full(obs.ant1.size, scene.integration),
    }
    sigma_col = np.repeat(sigma.astype(np.float32)[:, None], n_corr, axis=1)
    per_row["SIGMA"] = sigma_col
    per_row["WEIGHT"] = 1.0 / sigma_col ** 2
    inst = instrumental_series(scene, band_index, obs)
    blocks = [window_data(scene, band_index, w, obs, sigma, inst) for w in range(band.n_window)]
    if band.n_window == 1:
        per_row["DATA"] = blocks[0] if band.n_chan > 1 else blocks[0][:, 0, :]
        if band.is_wideband:
            per_row["DATA_DESC_ID"] = np.zeros(obs.ant1.size, np.int32)
        return per_row
    # (time, window, baseline) order: each time's rows of window 0, then window 1, ...
    n_row = obs.ant1.size
    window_of = np.repeat(np.arange(band.n_window, dtype=np.int32), n_row)
    order = np.lexsort((np.tile(np.arange(n_row), band.n_window), window_of,
                        np.tile(obs.time_index, band.n_window)))
    source_row = np.tile(np.arange(n_row), band.n_window)[order]
    columns = {name: value[source_row] for name, value in per_row.items()}
    columns["DATA"] = np.concatenate(blocks)[order]
    columns["DATA_DESC_ID"] = window_of[order]
    return columns
