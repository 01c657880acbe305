"""Wideband figures (PNG, matplotlib Agg, no pyplot state).

* ``waterfall-<A>-<B>.png``: phase over time (x, h) and frequency (y, GHz) for every
  compared column, one row per column (first correlation), cyclic colour map, with
  each channel's C(T) beside it (and each window's combined C as a black bar).  A
  channel whose phase is flat over time is a horizontal band of one colour; the
  troposphere shows as colour changing along time in every channel at once, a residual
  delay as colour changing along frequency.  Each window is drawn at its own
  frequencies, so the gaps between windows stay blank, and on a regular time axis, so
  scan gaps stay blank too.  Long tracks are vector-averaged into at most
  ``MAX_TIME_BINS`` time bins (the axis label says how many sampling intervals each spans).
* ``coherence-spectrum.png``: per-channel C(T) against frequency for every baseline,
  one panel per column, with each window's combined C (time and channels averaged
  together) as a horizontal bar across the window.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .plots import column_colours, mjd_label, new_figure
from .spectral import SpectralResult
from .spectral_read import SpectralGrid

#: waterfall time bins at most (a 12-h track of 1-s samples is averaged 72 to 1)
MAX_TIME_BINS = 600


def _binned(cube: np.ndarray, good: np.ndarray, bin_of_time: np.ndarray,
            n_bin: int) -> np.ndarray:
    """Phase of the vector average of the (n_time, n_chan) samples in each time bin
    (``bin_of_time`` ascending); NaN where a bin has no usable sample (e.g. scan gaps)."""
    starts = np.flatnonzero(np.r_[True, np.diff(bin_of_time) > 0])
    values = np.where(good, cube, 0)
    total = np.zeros((n_bin, cube.shape[1]), dtype=values.dtype)
    count = np.zeros((n_bin, cube.shape[1]), dtype=np.int64)
    total[bin_of_time[starts]] = np.add.reduceat(values, starts, axis=0)
    count[bin_of_time[starts]] = np.add.reduceat(good.astype(np.int64), starts, axis=0)
    with np.errstate(invalid="ignore"):
        return np.where((count > 0) & (np.abs(total) > 0), np.angle(total), np.nan)


def time_bins(times: np.ndarray, dt: float):
    """(bin of each time, number of bins, samples per bin) on the regular grid of step dt
    from the first time, so scan gaps keep their length on the time axis."""
    slot = np.rint((times - times[0]) / dt).astype(np.int64)
    n_slot = int(slot[-1]) + 1
    factor = max(1, math.ceil(n_slot / MAX_TIME_BINS))
    return slot // factor, math.ceil(n_slot / factor), factor


def _waterfall_axes(n_columns: int):
    """A figure with, per column, a waterfall panel and a narrow per-channel C(T) panel."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 2.8 * n_columns), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(n_columns, 2, width_ratios=[7, 1])
    rows = []
    for r in range(n_columns):
        left = fig.add_subplot(grid[r, 0])
        rows.append((left, fig.add_subplot(grid[r, 1], sharey=left)))
    return fig, rows


def waterfall_figure(grid: SpectralGrid, b: int, columns: Sequence[str], res: SpectralResult):
    """Phase against time and frequency on baseline ``b``, one row of panels per column:
    the waterfall (first correlation) and each channel's C(T) (correlation mean) beside it."""
    fig, rows = _waterfall_axes(len(columns))
    t0 = grid.times[0]
    bin_of_time, n_bin, factor = time_bins(grid.times, grid.dt)
    edges_t = (np.arange(n_bin + 1) * factor * grid.dt) / 3600.0
    name = grid.baseline_names[b]
    corr = 0
    mesh = None
    for (ax, side), col in zip(rows, columns):
        i = grid.columns.index(col)
        for w, freq in enumerate(grid.chan_freq):
            cube = grid.vis[w][b, :, i, :, corr]
            good = ~grid.flag[w][b, :, :, corr] & np.isfinite(cube) & (np.abs(cube) > 0)
            phase = _binned(cube, good, bin_of_time, n_bin)
            half = np.diff(freq).mean() / 2 if freq.size > 1 else 0.5e9
            edges_f = np.concatenate([freq - half, [freq[-1] + half]]) / 1e9
            mesh = ax.pcolormesh(edges_t, edges_f, phase.T, cmap="twilight", vmin=-np.pi,
                                 vmax=np.pi, shading="flat", rasterized=True)
            # window edges: adjacent windows would otherwise look like one
            ax.axhline(edges_f[0], color="white", lw=0.6, ls=":")
            ax.axhline(edges_f[-1], color="white", lw=0.6, ls=":")
            side.plot(res.per_channel[col][w][b], freq / 1e9, ".-", ms=2, lw=0.6,
                      color="tab:red", label="channel" if w == 0 else None)
            side.vlines(res.per_window[col][b, w], edges_f[0], edges_f[-1], colors="black",
                        lw=0.8, label="window" if w == 0 else None)
        c_all = res.all_channels[col][b]
        ax.set_title(f"{name} {grid.corr_names[corr]}  {col}  (C({res.interval:g} s) over all "
                     f"channels {c_all:.3f})", fontsize=9, loc="left")
        ax.set_ylabel("frequency (GHz)")
        side.set_xlim(0, 1.05)
        side.set_xticks([0, 0.5, 1])
        side.set_title(f"C({res.interval:g} s)", fontsize=8)
        side.tick_params(labelleft=False, labelsize=7)
    rows[0][1].legend(fontsize=6, loc="lower left", frameon=False)
    rows[-1][0].set_xlabel(f"time since {mjd_label(t0)} (h)"
                           + (f", bins of {factor} samples" if factor > 1 else ""))
    rows[-1][1].set_xlabel("per channel", fontsize=8)
    if mesh is not None:
        bar = fig.colorbar(mesh, ax=[r[0] for r in rows], location="left", fraction=0.03,
                           pad=0.01)
        bar.set_label("phase (rad)")
        bar.set_ticks([-np.pi, -np.pi / 2, 0, np.pi / 2, np.pi])
        bar.set_ticklabels(["-pi", "-pi/2", "0", "pi/2", "pi"])
    return fig


def spectrum_figure(res: SpectralResult):
    """Per-channel C(T) against frequency for every baseline, one panel per column."""
    fig, axes = new_figure(len(res.columns), panel_size=(8.0, 2.8))
    colours = column_colours(res.columns)
    for ax, col in zip(axes, res.columns):
        for b in range(len(res.baselines)):
            for w, freq in enumerate(res.chan_freq):
                ax.plot(freq / 1e9, res.per_channel[col][w][b], "-", lw=1.0, alpha=0.8,
                        color=colours[col], label="per channel (one line per baseline)"
                        if b == 0 and w == 0 else None)
                ax.hlines(res.per_window[col][b, w], freq.min() / 1e9, freq.max() / 1e9,
                          colors="black", lw=0.8, alpha=0.5,
                          label="window (time and channels averaged together)"
                          if b == 0 and w == 0 else None)
        ax.set_ylim(0, 1.02)
        ax.set_ylabel(f"C({res.interval:g} s)")
        ax.set_title(f"{col}: median over baselines, all channels "
                     f"{np.nanmedian(res.all_channels[col]):.3f}", fontsize=9, loc="left")
        ax.legend(fontsize=7, loc="lower left", frameon=False)
    axes[-1].set_xlabel("frequency (GHz)")
    return fig
