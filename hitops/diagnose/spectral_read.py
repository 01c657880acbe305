"""Read every channel of every spectral window onto one (baseline, time) grid.

Wideband data (several channels, several spectral windows of one field) are read
through the shared reader's grouping (:func:`hitops.io.read.open_groups`: one dask-ms
dataset per (FIELD_ID, DATA_DESC_ID), so windows with different channel counts are
fine) in one ``dask.compute``.  Every window's rows are laid out on the union of the
windows' times and baselines; a cell a window has no row for is flagged.

:func:`band_average` turns the channel cubes into the one-phase-per-sample grid the
coherence tables work on (the vector average of every unflagged channel of every
window), so a wideband set is read once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import numpy as np

from ..errors import MeasurementSetError
from ..io.layout import unique_times
from ..io.metadata import SetMetadata, read_metadata
from ..io.stations import stations_of
from .read import (BaselineNames, GridData, check_columns, check_ms, read_grid,
                   read_values_by_group,
                   sampling_interval, select_baselines, select_correlations)


@dataclass
class SpectralGrid(BaselineNames):
    """Selected baselines of one Measurement Set, every channel of every window."""

    ms: str
    antenna_names: List[str]
    ant1: np.ndarray                    # (n_bl,)
    ant2: np.ndarray                    # (n_bl,)
    times: np.ndarray                   # (n_time,) MJD seconds
    scan: np.ndarray                    # (n_bl, n_time) SCAN_NUMBER, -1 where no window has a row
    dt: float                           # sampling interval (s)
    columns: List[str]
    corr_names: List[str]
    spw_ids: List[int]                  # SPECTRAL_WINDOW_ID of each window, in frequency order
    chan_freq: List[np.ndarray]         # per window (n_chan_w,) Hz
    vis: List[np.ndarray]               # per window (n_bl, n_time, n_col, n_chan_w, n_corr)
    flag: List[np.ndarray]      # per window (n_bl, n_time, n_chan_w, n_corr); True: unusable
    uvw: Optional[np.ndarray] = None    # (n_bl, n_time, 3) m, NaN where no row
    warnings: List[str] = field(default_factory=list)

    @property
    def n_chan(self) -> int:
        return int(sum(f.size for f in self.chan_freq))


def is_spectral(ms: str) -> bool:
    """More than one channel or more than one spectral window in the DATA_DESCRIPTION table."""
    return spectral(read_metadata(ms))


def spectral(meta: SetMetadata) -> bool:
    """:func:`is_spectral` of a set's metadata already read."""
    used = sorted({d.window for d in meta.data_descriptions})
    return len(used) > 1 or any(meta.windows[s].num_chan > 1 for s in used)


def read_spectral(ms: str, columns: Sequence[str], *, correlations: Optional[str] = None,
                  baselines: Optional[str] = None, want_uvw: bool = False,
                  row_chunk: int = 400_000, meta: Optional[SetMetadata] = None) -> SpectralGrid:
    """Every channel of ``columns`` of ``ms`` for the selected baselines and correlations."""
    ms = str(ms)
    cols = list(dict.fromkeys(columns))
    check_columns(ms, cols)
    meta = read_metadata(ms) if meta is None else meta   # the caller's, read once
    ant_names = stations_of(ms, meta.antennas).codes
    wanted = ["TIME", "ANTENNA1", "ANTENNA2", "FLAG", "FLAG_ROW", "SCAN_NUMBER"] + cols
    if want_uvw:
        wanted.append("UVW")
    groups = read_values_by_group(ms, wanted, row_chunk, mixed=meta.has_groups())
    fields = sorted({f for f, _ in groups})
    if len(fields) > 1:
        raise MeasurementSetError(f"{ms} holds several fields (FIELD_ID {fields}); split them "
                                  "(e.g. CASA split by field) and diagnose each")
    keys = sorted(groups)
    values = [groups[k] for k in keys]
    spw_ids = [meta.window_of(ddid) for _, ddid in keys]
    pol_ids = {meta.data_descriptions[ddid].polarization for _, ddid in keys}
    if len(pol_ids) > 1:
        raise MeasurementSetError(f"{ms}: the spectral windows use different polarization "
                                  f"setups (POLARIZATION_ID {sorted(pol_ids)}); split them by spw")
    corr_idx, corr_names = select_correlations(meta.polarizations[pol_ids.pop()].corr_types,
                                               correlations, ms)
    freqs = [meta.windows[s].chan_freq for s in spw_ids]
    order = np.argsort([f.min() for f in freqs], kind="stable")
    values = [values[i] for i in order]
    spw_ids = [spw_ids[i] for i in order]
    freqs = [freqs[i] for i in order]
    for s, f in zip(spw_ids, freqs):
        if f.size > 1 and not np.all(np.diff(f) > 0):
            raise MeasurementSetError(f"{ms}: spectral window {s}'s CHAN_FREQ is not increasing "
                                      "(reversed or repeated channels); reorder it (CASA "
                                      "mstransform) before diagnosing")
    return _lay_out(ms, ant_names, values, cols, corr_idx, corr_names, spw_ids, freqs,
                    baselines, want_uvw)


def _lay_out(ms, ant_names, values, cols, corr_idx, corr_names, spw_ids, freqs, baselines,
             want_uvw) -> SpectralGrid:
    """Place every window's rows on the union (baseline, time) grid."""
    cross = [v["ANTENNA1"] != v["ANTENNA2"] for v in values]
    if not any(c.any() for c in cross):
        raise MeasurementSetError(f"{ms}: no cross-correlation rows (only autocorrelations)")
    n_ant = max(len(ant_names), 1)
    keys = [v["ANTENNA1"].astype(np.int64) * n_ant + v["ANTENNA2"] for v in values]
    pairs = np.unique(np.concatenate([k[c] for k, c in zip(keys, cross)]))
    mask = select_baselines(pairs // n_ant, pairs % n_ant, ant_names, baselines, ms)
    pairs = pairs[mask]
    keep = [c & np.isin(k, pairs) for k, c in zip(keys, cross)]
    times, time_of = unique_times(np.concatenate([v["TIME"][k] for v, k in zip(values, keep)]),
                                  1e-3)
    bounds = np.cumsum([0] + [int(k.sum()) for k in keep])
    n_bl, n_time = pairs.size, times.size
    scan = np.full((n_bl, n_time), -1, np.int32)
    uvw = np.full((n_bl, n_time, 3), np.nan) if want_uvw else None
    vis, flags = [], []
    for w, (v, k) in enumerate(zip(values, keep)):
        bl = np.searchsorted(pairs, keys[w][k])
        t = time_of[bounds[w]:bounds[w + 1]]
        cell = bl * n_time + t
        if np.unique(cell).size != cell.size:
            raise MeasurementSetError(f"{ms}: spectral window {spw_ids[w]} has several rows for "
                                      "one (TIME, ANTENNA1, ANTENNA2); split sub-arrays or "
                                      "scans before diagnosing")
        flag = v["FLAG"][k][..., corr_idx] | v["FLAG_ROW"][k][:, None, None]
        grid_flag = np.ones((n_bl, n_time) + flag.shape[1:], bool)
        grid_flag[bl, t] = flag
        cube = np.zeros((n_bl, n_time, len(cols)) + flag.shape[1:],
                        dtype=np.result_type(*[v[c].dtype for c in cols]))
        for i, col in enumerate(cols):
            cube[bl, t, i] = v[col][k][..., corr_idx]
        scan[bl, t] = v["SCAN_NUMBER"][k]
        if want_uvw:
            uvw[bl, t] = v["UVW"][k]
        vis.append(cube)
        flags.append(grid_flag)
    dt = sampling_interval(ms, times)
    return SpectralGrid(ms=ms, antenna_names=ant_names, ant1=(pairs // n_ant).astype(np.int32),
                        ant2=(pairs % n_ant).astype(np.int32), times=times, scan=scan, dt=dt,
                        columns=cols, corr_names=corr_names, spw_ids=spw_ids, chan_freq=freqs,
                        vis=vis, flag=flags, uvw=uvw)


def band_average(grid: SpectralGrid) -> GridData:
    """The grid the coherence tables use: each sample the vector average of its unflagged
    channels in every window (flagged where none is usable)."""
    total = None
    count = None
    for cube, flag in zip(grid.vis, grid.flag):
        good = ~flag                                         # (n_bl, n_time, n_chan, n_corr)
        part = (cube * good[:, :, None]).sum(axis=3)         # (n_bl, n_time, n_col, n_corr)
        n = good.sum(axis=2)
        total = part if total is None else total + part
        count = n if count is None else count + n
    stack = np.where(count[:, :, None] > 0, total / np.maximum(count, 1)[:, :, None], 0)
    stack = stack.astype(np.result_type(*[c.dtype for c in grid.vis]))
    warnings = list(grid.warnings) + [
        f"{grid.ms} has {grid.n_chan} channels in {len(grid.chan_freq)} spectral window(s): the "
        "coherence tables use each sample's vector average over every unflagged channel; the "
        "per-window and per-channel coherence is in summary.json ('spectral') and "
        "spectral-table.csv"]
    all_freq = np.concatenate(grid.chan_freq)
    return GridData(ms=grid.ms, antenna_names=grid.antenna_names, ant1=grid.ant1, ant2=grid.ant2,
                    times=grid.times, scan=grid.scan, flag=count == 0,
                    vis={c: stack[:, :, i, :] for i, c in enumerate(grid.columns)},
                    vis_stack=stack, corr_names=grid.corr_names, dt=grid.dt,
                    freq_hz=float(all_freq.mean()), uvw=grid.uvw, warnings=warnings)


def read_band(ms: str, columns: Sequence[str], **selection) -> GridData:
    """One phase per sample whatever the layout: one channel as it is, several channels or
    windows vector-averaged (:func:`band_average`)."""
    check_ms(str(ms))
    meta = read_metadata(str(ms))
    if spectral(meta):
        return band_average(read_spectral(str(ms), columns, meta=meta, **selection))
    return read_grid(str(ms), columns, meta=meta, **selection)
