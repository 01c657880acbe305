"""Diagnostic figures (PNG, matplotlib Agg, no pyplot state).

* ``phase-<A>-<B>.png``: phase (deg) against time (h) for every compared
  column, one panel per correlation, with dashed lines at the reference
  band's wrap times when ``--ref-ms`` is given (paper, Figures 1-3);
* ``coherence-<A>-<B>.png``: correlation-mean C(T) against T (s, log axis)
  for every column with the 1/e level and each column's tau_c (paper,
  Figure 4), and ``coherence-all.png`` with one panel per baseline;
* ``uv-coverage.png``: (u,v) tracks (G-lambda) coloured by the ratio of a
  later column's C(T) to the first column's, one panel per later column.

Every function returns the :class:`matplotlib.figure.Figure` it saved, so
tests can count panels and read the rendered pixels.
"""

from __future__ import annotations

import datetime as _dt
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from .metrics import INV_E, CoherenceResult
from .read import GridData

_MJD0 = _dt.datetime(1858, 11, 17, tzinfo=_dt.timezone.utc)
COLOURS = ["tab:green", "tab:blue", "tab:orange", "tab:red", "tab:purple", "tab:brown"]
C_LIGHT = 299_792_458.0


def _figure(n_panels: int, ncols: int = 1, panel_size=(8.0, 3.0)):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    nrows = int(math.ceil(n_panels / ncols))
    fig = Figure(figsize=(panel_size[0] * ncols, panel_size[1] * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(nrows, ncols, i + 1) for i in range(n_panels)]
    return fig, axes


def mjd_label(t_mjd_s: float) -> str:
    return (_MJD0 + _dt.timedelta(seconds=float(t_mjd_s))).strftime("%Y-%m-%d %H:%M:%S UTC")


def phase_figure(data: GridData, b: int, columns: Sequence[str],
                 wrap_times: Optional[Dict[str, np.ndarray]] = None,
                 time_range: Optional[tuple] = None, ref_label: str = "reference"):
    """Phase against time on baseline ``b``, one panel per correlation."""
    fig, axes = _figure(len(data.corr_names))
    t0 = data.times[0]
    hours = (data.times - t0) / 3600.0
    sel = np.ones(data.n_time, bool)
    if time_range is not None:
        rel = data.times - t0
        sel = (rel >= time_range[0]) & (rel <= time_range[1])
    name = data.baseline_name(b)
    for c, (ax, corr) in enumerate(zip(axes, data.corr_names)):
        for i, col in enumerate(columns):
            v = data.vis[col][b, :, c]
            ok = sel & ~data.flag[b, :, c] & np.isfinite(v) & (np.abs(v) > 0)
            ax.plot(hours[ok], np.degrees(np.angle(v[ok])), ".", ms=1.0,
                    color=COLOURS[i % len(COLOURS)], label=col, rasterized=True)
        if wrap_times is not None and corr in wrap_times and wrap_times[corr].size:
            wt = (wrap_times[corr] - t0) / 3600.0
            if time_range is not None:
                wt = wt[(wt * 3600 >= time_range[0]) & (wt * 3600 <= time_range[1])]
            ax.vlines(wt, -180, 180, colors="0.4", linestyles="dashed", linewidth=0.6,
                      label=f"{ref_label} wraps ({wrap_times[corr].size})")
        ax.set_ylim(-180, 180)
        ax.set_yticks([-180, -90, 0, 90, 180])
        ax.set_ylabel(f"{corr} phase (deg)")
        ax.set_title(f"{name} {corr}", fontsize=9, loc="left")
        # legend above the panel, so it never hides data
        ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=7, markerscale=6,
                  ncols=len(columns) + 1, frameon=False, borderaxespad=0.1)
    axes[-1].set_xlabel(f"time since {mjd_label(t0)} (h)")
    return fig


def coherence_axes(ax, res: CoherenceResult, b: int, name: str, small: bool = False):
    for i, col in enumerate(res.columns):
        curve = res.curve(col)[b]
        ok = np.isfinite(curve)
        if ok.any():
            ax.plot(res.intervals[ok], curve[ok], "-o", ms=2 if small else 3,
                    color=COLOURS[i % len(COLOURS)], label=col)
    ax.axhline(INV_E, color="0.5", linestyle=":", linewidth=0.8, label="1/e")
    ax.set_xscale("log")
    ax.set_ylim(0, 1.05)
    ax.set_title(name, fontsize=8 if small else 10)
    if not small:
        ax.set_xlabel("averaging interval T (s)")
        ax.set_ylabel("coherence factor C(T)")


def coherence_figure(res: CoherenceResult, b: int, name: str, records: List[dict]):
    """Correlation-mean C(T) against T on one baseline, with tau_c markers."""
    fig, (ax,) = _figure(1, panel_size=(6.5, 4.0))
    coherence_axes(ax, res, b, name)
    rec = records[b]
    for i, col in enumerate(res.columns):
        entry = rec["columns"][col]
        if entry["tau_c_bound"] == "=":
            ax.axvline(entry["tau_c_s"], color=COLOURS[i % len(COLOURS)], linestyle="--",
                       linewidth=0.7)
    ax.legend(fontsize=8, loc="lower left")
    return fig


def coherence_overview(res: CoherenceResult, names: List[str]):
    """C(T) of every baseline, one small panel each."""
    n = len(names)
    ncols = min(4, n)
    fig, axes = _figure(n, ncols=ncols, panel_size=(3.2, 2.3))
    for b, (ax, name) in enumerate(zip(axes, names)):
        coherence_axes(ax, res, b, name, small=True)
    axes[0].legend(fontsize=6, loc="lower left")
    fig.supxlabel("averaging interval T (s)")
    fig.supylabel("coherence factor C(T)")
    return fig


def uv_figure(data: GridData, res: CoherenceResult, records: List[dict], step_s: float = 60.0):
    """(u,v) tracks coloured by C_after / C_before at the metric interval."""
    from matplotlib import colors as mcolors

    before = res.columns[0]
    later = res.columns[1:] or res.columns[:1]
    fig, axes = _figure(len(later), ncols=min(2, len(later)), panel_size=(5.5, 5.0))
    lam = C_LIGHT / data.freq_hz
    stride = max(1, int(round(step_s / data.dt)))
    ratios = {}
    for col in later:
        r = np.array([np.nan if (rec["columns"][col]["coherence_factor"] is None or
                                 not rec["columns"][before]["coherence_factor"])
                      else rec["columns"][col]["coherence_factor"]
                      / rec["columns"][before]["coherence_factor"] for rec in records])
        ratios[col] = r
    finite = np.concatenate([r[np.isfinite(r)] for r in ratios.values()] or [np.array([1.0])])
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (1.0, 1.0)
    if hi - lo < 1e-6:
        lo, hi = lo - 0.05, hi + 0.05
    norm = mcolors.Normalize(vmin=lo, vmax=hi)
    for ax, col in zip(axes, later):
        ratio = ratios[col]
        for b in range(data.n_bl):
            uv = data.uvw[b, ::stride, :2] / lam / 1e9
            ok = np.all(np.isfinite(uv), axis=1)
            if not ok.any():
                continue
            value = np.full(ok.sum(), ratio[b])
            for sign in (1.0, -1.0):
                if np.isfinite(ratio[b]):
                    ax.scatter(sign * uv[ok, 0], sign * uv[ok, 1], c=value, s=2,
                                    cmap="viridis", norm=norm, rasterized=True)
                else:
                    ax.scatter(sign * uv[ok, 0], sign * uv[ok, 1], s=2, color="0.7",
                               rasterized=True)
        ax.set_aspect("equal")
        ax.invert_xaxis()
        ax.set_xlabel("u (G$\\lambda$)")
        ax.set_ylabel("v (G$\\lambda$)")
        ax.set_title(f"C({res.interval:g} s): {col} / {before}", fontsize=9)
        from matplotlib.cm import ScalarMappable
        fig.colorbar(ScalarMappable(norm=norm, cmap="viridis"), ax=ax,
                     label=f"C({col}) / C({before})", shrink=0.8)
    return fig


def save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
