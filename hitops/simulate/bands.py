"""One band's main-table columns: model x station phases + thermal noise, per window.

A band holds one or more spectral windows of n_chan channels each
(:class:`hitops.simulate.scene_parts.BandSpec`).  Per window and channel k:

* troposphere: phase 2 pi nu_k L_p(t) / c of each station's excess path, i.e.
  (nu_k / nu_0) x the phase at the coherence frequency nu_0;
* instrumental (optional, per station and band): phase + 2 pi (nu_k - nu_band) x delay,
  both constant or drifting linearly;
* thermal noise from the radiometer equation with the channel width as bandwidth.

Rows of a band with several windows are ordered by (time, window, baseline), as a
correlator writes them, with DATA_DESC_ID = window index.  Wideband columns come in
blocks of whole times (:func:`band_blocks`), so memory stays bounded whatever the size
of the set; each window's noise is drawn block after block from one generator, so the
data do not depend on the block size.
"""

from __future__ import annotations

from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np

from .. import radiometer
from .kernels import corrupt_channels
from .sources import field_visibilities, model_visibilities


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


#: visibilities (rows x channels x correlations, all windows) computed and written at once:
#: ~64 MB of complex64 DATA per block, a few times that in temporaries
BLOCK_VISIBILITIES = 1 << 23


def row_blocks(time_index: np.ndarray, max_rows: int) -> List[slice]:
    """Consecutive row ranges of at most ``max_rows`` rows, cut where the time changes
    (rows are time-major); a time with more rows than that is a block of its own."""
    n_row = time_index.size
    bounds = np.r_[np.flatnonzero(np.r_[True, np.diff(time_index) != 0]), n_row]
    blocks, first = [], 0
    while first < n_row:
        cut = int(bounds[np.searchsorted(bounds, first + max_rows, side="right") - 1])
        if cut <= first:
            cut = int(bounds[np.searchsorted(bounds, first, side="right")])
        blocks.append(slice(first, cut))
        first = cut
    return blocks


def _noise_generator(scene, band_index: int, window: int):
    # window 0 draws exactly the stream of the single-channel simulator
    key = [scene.seed, 2, band_index] + ([window] if window else [])
    return np.random.default_rng(np.random.SeedSequence(key))


def writes_model(scene) -> bool:
    """MODEL_DATA is written only for a resolved calibrator (``calibrator.components``):
    scenes without one keep their sets as they were."""
    return scene.calibrator is not None and bool(scene.calibrator.components)


def window_model(scene, band_index: int, window: int, obs, rows: slice) -> np.ndarray:
    """Noise-free visibilities (n_row, n_chan) complex128 of one window: the target's
    model on its rows, the calibrator's (point + components, at its own phase centre)
    on the calibrator's."""
    band = scene.bands[band_index]
    chan_freq = band.chan_freq()[window]
    model = model_visibilities(scene, band.name, obs.uvw[rows], chan_freq)
    if obs.field_id is not None:
        on_cal = obs.field_id[obs.time_index[rows]] == 1
        cal = scene.calibrator
        model[on_cal] = field_visibilities(cal.flux, cal.components, band.name,
                                           obs.uvw[rows][on_cal], chan_freq)
    return model


def model_column(scene, model: np.ndarray, obs, rows: slice) -> np.ndarray:
    """MODEL_DATA (n_row, n_chan, n_corr) complex64 as CASA's ft/setjy write a Stokes I
    model: the calibrator's visibility on its rows in the parallel hands, 0 in the cross
    hands; the target's rows 1 (CASA's default model: the target's structure is what
    the observer wants to find, so the simulator does not hand it to calibration)."""
    parallel = np.array([c[0] == c[1] for c in scene.correlations])
    on_cal = obs.field_id[obs.time_index[rows]] == 1
    values = np.where(on_cal[:, None], model, 1.0)
    return (values[:, :, None] * parallel[None, None, :]).astype(np.complex64)


def window_block(scene, band_index: int, window: int, obs, rows: slice, sigma: np.ndarray,
                 inst: Optional[Tuple[np.ndarray, np.ndarray]], rng,
                 model: np.ndarray) -> np.ndarray:
    """DATA (n_row, n_chan, n_corr) complex64 of one window for the rows ``rows``
    (``inst``: :func:`instrumental_series`; ``rng``: the window's noise generator, None
    for noise-free data, drawn in row order so blocks give the stream of one draw;
    ``model``: :func:`window_model`)."""
    band = scene.bands[band_index]
    chan_freq = band.chan_freq()[window]
    n_corr = len(scene.correlations)
    n_row = obs.ant1[rows].size
    parallel = np.array([c[0] == c[1] for c in scene.correlations])
    if rng is not None:
        draws = rng.standard_normal((n_row, chan_freq.size, n_corr, 2), dtype=np.float32)
    else:
        draws = np.zeros((0, chan_freq.size, n_corr, 2), np.float32)
    if inst is None:
        inst = (np.zeros((0, 0)), np.zeros((0, 0)))
    return corrupt_channels(model,
                            obs.ant1[rows], obs.ant2[rows], obs.time_index[rows],
                            obs.phase_ref, chan_freq / scene.coherence_freq_hz, inst[0], inst[1],
                            chan_freq - band.freq_hz, parallel, draws, sigma[rows])


def band_blocks(scene, band_index: int, obs,
                max_visibilities: Optional[int] = None) -> Iterator[Dict[str, np.ndarray]]:
    """Main-table columns of one band's Measurement Set, block after block of whole times
    (all windows of those times), in the set's row order.  A one-channel band comes in one
    block (DATA (n_row, 1, n_corr)), exactly as the single-channel simulator made it."""
    band = scene.bands[band_index]
    n_corr = len(scene.correlations)
    sigma = band_sigma(scene, band_index, obs)
    inst = instrumental_series(scene, band_index, obs)
    rngs = [_noise_generator(scene, band_index, w) if scene.noise else None
            for w in range(band.n_window)]
    per_row_vis = band.n_window * band.n_chan * n_corr
    budget = max_visibilities or BLOCK_VISIBILITIES
    max_rows = obs.ant1.size if not band.is_wideband else max(1, budget // per_row_vis)
    for rows in row_blocks(obs.time_index, max_rows):
        sigma_col = np.repeat(sigma[rows].astype(np.float32)[:, None], n_corr, axis=1)
        per_row = {
            "TIME": obs.times[obs.time_index[rows]],
            "ANTENNA1": obs.ant1[rows],
            "ANTENNA2": obs.ant2[rows],
            "UVW": obs.uvw[rows],
            "SCAN_NUMBER": obs.scan[obs.time_index[rows]],
            "INTERVAL": np.full(obs.ant1[rows].size, scene.integration),
            "SIGMA": sigma_col,
            "WEIGHT": 1.0 / sigma_col ** 2,
        }
        if obs.field_id is not None:
            per_row["FIELD_ID"] = obs.field_id[obs.time_index[rows]]
        models = [window_model(scene, band_index, w, obs, rows) for w in range(band.n_window)]
        blocks = [window_block(scene, band_index, w, obs, rows, sigma, inst, rngs[w], models[w])
                  for w in range(band.n_window)]
        model_blocks = ([model_column(scene, m, obs, rows) for m in models]
                        if writes_model(scene) else None)
        yield _interleave(per_row, blocks, obs.time_index[rows], band.is_wideband, model_blocks)


def _interleave(per_row: Dict[str, np.ndarray], blocks, time_index: np.ndarray,
                wideband: bool, model_blocks=None) -> Dict[str, np.ndarray]:
    """Rows in (time, window, baseline) order: each time's rows of window 0, then window 1...
    (``model_blocks``: MODEL_DATA per window, or None: no MODEL_DATA)."""
    n_row, n_window = time_index.size, len(blocks)
    if n_window == 1:
        columns = dict(per_row, DATA=blocks[0])
        if model_blocks is not None:
            columns["MODEL_DATA"] = model_blocks[0]
        if wideband:
            columns["DATA_DESC_ID"] = np.zeros(n_row, np.int32)
        return columns
    window_of = np.repeat(np.arange(n_window, dtype=np.int32), n_row)
    order = np.lexsort((np.tile(np.arange(n_row), n_window), window_of,
                        np.tile(time_index, n_window)))
    source_row = np.tile(np.arange(n_row), n_window)[order]
    columns = {name: value[source_row] for name, value in per_row.items()}
    columns["DATA"] = np.concatenate(blocks)[order]
    if model_blocks is not None:
        columns["MODEL_DATA"] = np.concatenate(model_blocks)[order]
    columns["DATA_DESC_ID"] = window_of[order]
    return columns
