"""Coherence of wideband data: per channel, per spectral window and across all channels.

At the averaging interval T of ``--interval`` (the kernel and rules of
:mod:`hitops.kernels.coherence`: segments [t0 + kT, t0 + (k+1)T) within a scan,
``min_fill``, segment-weighted mean, correlation mean):

* per channel: C_k(T) of each channel's own phase series;
* per window: C of the vector average over time *and* the window's channels,
  |sum_{t in seg, k in window} e^{i phi_tk}| / n, per segment, then averaged over
  segments.  A channel-to-channel phase slope (a residual delay, or one ratio per
  window applied to an excess path) lowers it even when every channel alone is
  coherent; it is what imaging or fringe fitting across the window keeps;
* all channels: the same over every channel of every window.

The window and all-channel values reuse the segment kernel by laying a sample's
channels out along time: channel k of the sample at t sits at t + k dt / n_chan,
so each segment of whole samples holds all their channels (exactly when T is a
multiple of the sampling interval).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List

import numpy as np

from .metrics import compute_coherence, nanmean_or_nan
from .spectral_read import SpectralGrid

SPECTRAL_CSV = "spectral-table.csv"


@dataclass
class SpectralResult:
    """C(T) at one interval of every channel, window and of all channels, per column."""

    interval: float
    columns: List[str]
    baselines: List[str]
    spw_ids: List[int]
    chan_freq: List[np.ndarray]                   # per window (n_chan_w,) Hz
    per_channel: Dict[str, List[np.ndarray]]      # column -> per window (n_bl, n_chan_w)
    per_window: Dict[str, np.ndarray]             # column -> (n_bl, n_window)
    all_channels: Dict[str, np.ndarray]           # column -> (n_bl,)


def _corr_mean(c_mean: np.ndarray) -> np.ndarray:
    """(n, n_corr, 1) -> (n,): the mean over correlations with data at the one interval."""
    return nanmean_or_nan(c_mean[:, :, 0], axis=1)


def _channels_as_series(grid: SpectralGrid, cube: np.ndarray, flag: np.ndarray, interval: float,
                        min_fill: float) -> Dict[str, np.ndarray]:
    """Per-channel C: channels folded into the baseline axis. -> column -> (n_bl, n_chan)."""
    n_bl, n_time, n_col, n_chan, n_corr = cube.shape
    vis = cube.transpose(0, 3, 1, 2, 4).reshape(n_bl * n_chan, n_time, n_col, n_corr)
    flg = flag.transpose(0, 2, 1, 3).reshape(n_bl * n_chan, n_time, n_corr)
    scan = np.repeat(grid.scan, n_chan, axis=0)
    res = compute_coherence(vis, grid.columns, flg, grid.times, scan, grid.dt,
                            np.array([interval]), interval, min_fill=min_fill)
    return {c: _corr_mean(res.c_mean[c][:, :, [res.k_interval]]).reshape(n_bl, n_chan)
            for c in grid.columns}


def _channels_along_time(grid: SpectralGrid, cube: np.ndarray, flag: np.ndarray,
                         interval: float, min_fill: float) -> Dict[str, np.ndarray]:
    """C over time and channels together: channels laid out along time. -> column -> (n_bl,)."""
    n_bl, n_time, n_col, n_chan, n_corr = cube.shape
    vis = cube.transpose(0, 1, 3, 2, 4).reshape(n_bl, n_time * n_chan, n_col, n_corr)
    flg = flag.reshape(n_bl, n_time * n_chan, n_corr)
    step = grid.dt / n_chan
    times = (grid.times[:, None] + step * np.arange(n_chan)[None, :]).ravel()
    scan = np.repeat(grid.scan, n_chan, axis=1)
    res = compute_coherence(vis, grid.columns, flg, times, scan, step,
                            np.array([interval]), interval, min_fill=min_fill)
    return {c: _corr_mean(res.c_mean[c][:, :, [res.k_interval]]) for c in grid.columns}


def spectral_coherence(grid: SpectralGrid, interval: float, min_fill: float) -> SpectralResult:
    """Per-channel, per-window and all-channel coherence at ``interval`` (s)."""
    per_channel = {c: [] for c in grid.columns}
    per_window = {c: np.empty((grid.n_bl, len(grid.vis))) for c in grid.columns}
    for w, (cube, flag) in enumerate(zip(grid.vis, grid.flag)):
        for col, values in _channels_as_series(grid, cube, flag, interval, min_fill).items():
            per_channel[col].append(values)
        for col, values in _channels_along_time(grid, cube, flag, interval, min_fill).items():
            per_window[col][:, w] = values
    if len(grid.vis) == 1:
        all_channels = {c: per_window[c][:, 0].copy() for c in grid.columns}
    else:
        cube = np.concatenate(grid.vis, axis=3)
        flag = np.concatenate(grid.flag, axis=2)
        all_channels = _channels_along_time(grid, cube, flag, interval, min_fill)
    return SpectralResult(interval=float(interval), columns=list(grid.columns),
                          baselines=grid.baseline_names, spw_ids=list(grid.spw_ids),
                          chan_freq=list(grid.chan_freq), per_channel=per_channel,
                          per_window=per_window, all_channels=all_channels)


def _num(x) -> object:
    return None if not np.isfinite(x) else round(float(x), 6)


def summary_section(res: SpectralResult) -> dict:
    """The 'spectral' section of summary.json."""
    windows = [{"spw": int(s), "n_chan": int(f.size), "freq_min_hz": float(f.min()),
                "freq_max_hz": float(f.max())} for s, f in zip(res.spw_ids, res.chan_freq)]
    columns = {}
    for col in res.columns:
        baselines = {}
        for b, name in enumerate(res.baselines):
            chans = [res.per_channel[col][w][b] for w in range(len(res.spw_ids))]
            baselines[name] = {
                "all_channels": _num(res.all_channels[col][b]),
                "windows": [_num(v) for v in res.per_window[col][b]],
                "channel_min": [_num(np.nanmin(c)) if np.isfinite(c).any() else None
                                for c in chans],
                "channels": [[_num(v) for v in c] for c in chans],
            }
        every = np.concatenate([np.concatenate(res.per_channel[col], axis=1).ravel()])
        columns[col] = {
            "baselines": baselines,
            "median_all_channels": _num(np.nanmedian(res.all_channels[col]))
            if np.isfinite(res.all_channels[col]).any() else None,
            "median_windows": [_num(np.nanmedian(res.per_window[col][:, w]))
                               if np.isfinite(res.per_window[col][:, w]).any() else None
                               for w in range(len(res.spw_ids))],
            "min_channel": _num(np.nanmin(every)) if np.isfinite(every).any() else None,
        }
    return {"interval_s": res.interval, "windows": windows, "columns": columns}


def write_csv(path: Path, res: SpectralResult) -> None:
    """One row per (column, baseline, window) plus an 'all' row per (column, baseline)."""
    with open(path, "w", newline="") as handle:
        out = csv.writer(handle)
        out.writerow(["column", "baseline", "window", "freq_min_ghz", "freq_max_ghz", "n_chan",
                      "c_window", "c_channel_min", "c_channel_median", "c_channel_max",
                      "interval_s"])
        for col in res.columns:
            for b, name in enumerate(res.baselines):
                rows = []
                for w, spw in enumerate(res.spw_ids):
                    chans = res.per_channel[col][w][b]
                    rows.append((str(spw), res.chan_freq[w], res.per_window[col][b, w], chans))
                every = np.concatenate([r[3] for r in rows])
                rows.append(("all", np.concatenate(res.chan_freq), res.all_channels[col][b],
                             every))
                for label, freq, c_window, chans in rows:
                    finite = chans[np.isfinite(chans)]
                    stats = ([f"{np.min(finite):.6f}", f"{np.median(finite):.6f}",
                              f"{np.max(finite):.6f}"] if finite.size else ["", "", ""])
                    out.writerow([col, name, label, f"{freq.min() / 1e9:.6f}",
                                  f"{freq.max() / 1e9:.6f}", freq.size,
                                  f"{c_window:.6f}" if np.isfinite(c_window) else ""] + stats
                                 + [f"{res.interval:g}"])


def render_text(section: dict) -> str:
    """A few lines for coherence-table.txt: array medians per window and across all channels."""
    lines = [f"Wideband coherence at T = {section['interval_s']:g} s "
             f"({len(section['windows'])} window(s)):"]
    for w in section["windows"]:
        lines.append(f"  window {w['spw']}: {w['n_chan']} channels, "
                     f"{w['freq_min_hz'] / 1e9:.4f}-{w['freq_max_hz'] / 1e9:.4f} GHz")
    for col, entry in section["columns"].items():
        windows = ", ".join("-" if v is None else f"{v:.4f}" for v in entry["median_windows"])
        every = entry["median_all_channels"]
        worst = entry["min_channel"]
        lines.append(f"  {col}: median over baselines per window [{windows}], all channels "
                     f"{'-' if every is None else f'{every:.4f}'}, worst channel "
                     f"{'-' if worst is None else f'{worst:.4f}'}")
    return "\n".join(lines) + "\n"
