"""Diagnostic figures (PNG, matplotlib Agg, no pyplot state).

* ``phase-<A>-<B>.png``: phase (deg) against time (h) for every compared
  column, one panel per correlation, with dashed lines at the reference
  band's wrap times when ``--ref-ms`` is given (paper, Figures 1-3);
* ``coherence-<A>-<B>.png``: correlation-mean C(T) against T (s, log axis)
  for every column with the 1/e level and each column's tau_c (paper,
  Figure 4), and ``coherence-all.png`` with one panel per baseline;
* ``uv-coverage.png``: (u,v) tracks (G-lambda) coloured by the ratio of a
  later column's C(T) to the first column's, one panel per later column.

Every method has one colour in every plot (:data:`METHOD_COLOURS`: raw DATA,
FF+SC CORRECTED_DATA, CFPT, CWU, PWC, PWC with no control PWC_NC_DATA),
whatever the order of ``--columns``;
other columns get the next free colours.  A series identical to one drawn
before it (CWU and PWC agree wherever no wrap was missed) is drawn on top with
open markers and a dashed line, and its legend entry says which it equals, so
both stay visible.  Legends explain every line, including the dashed tau_c
markers and the 1/e level.

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
C_LIGHT = 299_792_458.0

#: The colour of each method, the same in every plot and every run
METHOD_COLOURS = {"raw": "tab:green", "ffsc": "tab:blue", "cfpt": "tab:orange",
                  "cwu": "tab:purple", "pwc": "tab:red", "pwcnc": "tab:brown"}
#: Column names of the methods (hitops calibrate's outputs and CASA's FF+SC column)
COLUMN_METHODS = {"DATA": "raw", "CORRECTED_DATA": "ffsc", "CFPT_DATA": "cfpt",
                  "CWU_DATA": "cwu", "PWC_DATA": "pwc", "PWC_NC_DATA": "pwcnc"}
#: Colours of other columns (e.g. PWC230_DATA), in the order they appear
OTHER_COLOURS = ["tab:pink", "tab:olive", "tab:cyan", "tab:gray", "black"]
#: Every colour a plot uses: the methods' (raw, CFPT, PWC, FF+SC, CWU, PWC with no
#: control), then the others
COLOURS = [METHOD_COLOURS[m] for m in ("raw", "cfpt", "pwc", "ffsc", "cwu", "pwcnc")] \
    + OTHER_COLOURS


def column_colours(columns: Sequence[str]) -> Dict[str, str]:
    """Colour of each column: its method's, or the next colour no method uses."""
    out: Dict[str, str] = {}
    spare = iter(OTHER_COLOURS * 4)
    for col in columns:
        method = COLUMN_METHODS.get(col.upper())
        out[col] = METHOD_COLOURS[method] if method else next(spare)
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Two series equal wherever both are defined (and defined at the same places)."""
    if a.shape != b.shape:
        return False
    fa, fb = np.isfinite(a), np.isfinite(b)
    return bool(np.array_equal(fa, fb) and fa.any()
                and np.allclose(a[fa], b[fb], rtol=1e-6, atol=1e-9))


def _identical_to(series: Dict[str, np.ndarray], columns: Sequence[str]) -> Dict[str, str]:
    """For each column, the first earlier column it is identical to (if any)."""
    out = {}
    for i, col in enumerate(columns):
        for prev in columns[:i]:
            if prev not in out and _same(series[col], series[prev]):
                out[col] = prev
                break
    return out


def new_figure(n_panels: int, ncols: int = 1, panel_size=(8.0, 3.0)):
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
    fig, axes = new_figure(len(data.corr_names))
    t0 = data.times[0]
    hours = (data.times - t0) / 3600.0
    sel = np.ones(data.n_time, bool)
    if time_range is not None:
        rel = data.times - t0
        sel = (rel >= time_range[0]) & (rel <= time_range[1])
    name = data.baseline_name(b)
    from matplotlib.lines import Line2D

    colours = column_colours(columns)
    legend: Dict[str, object] = {}
    for c, (ax, corr) in enumerate(zip(axes, data.corr_names)):
        phases = {}
        for col in columns:
            v = data.vis[col][b, :, c]
            ok = sel & ~data.flag[b, :, c] & np.isfinite(v) & (np.abs(v) > 0)
            phases[col] = np.where(ok, np.degrees(np.angle(v)), np.nan)
        same = _identical_to(phases, columns)
        for col in columns:
            ok = np.isfinite(phases[col])
            label = col
            if col in same:
                # identical to a series drawn before it: drawn on top at every other
                # sample only, so that the two colours alternate along the same track
                ok &= (np.cumsum(ok) % 2) == 0
                label = f"{col} (= {same[col]}, every 2nd sample)"
            ax.plot(hours[ok], phases[col][ok], ".", ms=1.0, color=colours[col],
                    label=label, rasterized=True)
            legend.setdefault(label, Line2D([], [], linestyle="none", marker="o", ms=4,
                                            color=colours[col]))
        if wrap_times is not None and corr in wrap_times and wrap_times[corr].size:
            wt = (wrap_times[corr] - t0) / 3600.0
            if time_range is not None:
                wt = wt[(wt * 3600 >= time_range[0]) & (wt * 3600 <= time_range[1])]
            label = f"{ref_label} phase wraps (dashed)"
            ax.vlines(wt, -180, 180, colors="0.4", linestyles="dashed", linewidth=0.6,
                      label=label)
            legend.setdefault(label, Line2D([], [], color="0.4", linestyle="--", linewidth=0.8))
        ax.set_ylim(-180, 180)
        ax.set_yticks([-180, -90, 0, 90, 180])
        ax.set_ylabel(f"{corr} phase (deg)")
        ax.set_title(f"{name} {corr}", fontsize=9, loc="left")
    # one legend above the panels, so it neither hides data nor the panel titles
    fig.legend(list(legend.values()), list(legend), loc="outside upper center",
               ncols=min(len(legend), 3), fontsize=8, frameon=False)
    axes[-1].set_xlabel(f"time since {mjd_label(t0)} (h)")
    return fig


def coherence_axes(ax, res: CoherenceResult, b: int, name: str, small: bool = False):
    colours = column_colours(res.columns)
    curves = {col: np.asarray(res.curve(col)[b], dtype=float) for col in res.columns}
    same = _identical_to(curves, res.columns)
    drawn = 0
    for col in res.columns:
        curve = curves[col]
        ok = np.isfinite(curve)
        if not ok.any():
            continue
        drawn += 1
        if col in same:
            # on top of the identical curve, dashed with open markers: both stay visible
            ax.plot(res.intervals[ok], curve[ok], "--o", ms=4 if small else 6, mfc="none",
                    lw=1.0, color=colours[col], label=f"{col} (= {same[col]})")
        else:
            ax.plot(res.intervals[ok], curve[ok], "-o", ms=2 if small else 3,
                    color=colours[col], label=col)
    ax.axhline(INV_E, color="0.5", linestyle=":", linewidth=0.8, label="1/e")
    ax.set_xscale("log")
    ax.set_ylim(0, 1.05)
    ax.set_title(name, fontsize=8 if small else 10)
    if not drawn:
        ax.text(0.5, 0.5, "no unflagged data", transform=ax.transAxes, ha="center",
                va="center", fontsize=8, color="0.4")
    if not small:
        ax.set_xlabel("averaging interval T (s)")
        ax.set_ylabel("coherence factor C(T)")


def coherence_figure(res: CoherenceResult, b: int, name: str, records: List[dict]):
    """Correlation-mean C(T) against T on one baseline, with tau_c markers."""
    from matplotlib.lines import Line2D

    fig, (ax,) = new_figure(1, panel_size=(6.5, 4.0))
    coherence_axes(ax, res, b, name)
    rec = records[b]
    colours = column_colours(res.columns)
    marked = []
    for col in res.columns:
        entry = rec["columns"][col]
        if entry["tau_c_bound"] == "=":
            ax.axvline(entry["tau_c_s"], color=colours[col], linestyle="--", linewidth=0.7)
            marked.append(col)
    handles, labels = ax.get_legend_handles_labels()
    if marked:
        # one entry explains every dashed vertical line
        handles.append(Line2D([], [], color="0.3", linestyle="--", linewidth=0.7))
        labels.append("coherence time tau_c (C = 1/e),\nin the colour of its column")
    ax.legend(handles, labels, fontsize=8, loc="lower left")
    return fig


def coherence_overview(res: CoherenceResult, names: List[str]):
    """C(T) of every baseline, one small panel each."""
    n = len(names)
    ncols = min(4, n)
    fig, axes = new_figure(n, ncols=ncols, panel_size=(3.2, 2.3))
    for b, (ax, name) in enumerate(zip(axes, names)):
        coherence_axes(ax, res, b, name, small=True)
    # one legend for the figure, readable: in the free cells of the last row if any,
    # else above the panels; it gathers the entries of every panel
    entries: Dict[str, object] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    nrows = int(math.ceil(n / ncols))
    free = nrows * ncols - n
    if free:
        spot = fig.add_subplot(nrows, ncols, (n + 1, nrows * ncols))
        spot.axis("off")
        spot.legend(list(entries.values()), list(entries), loc="center", fontsize=9,
                    frameon=False, title="per panel: C(T) of each column")
    else:
        fig.legend(list(entries.values()), list(entries), loc="outside upper center",
                   ncols=min(len(entries), 6), fontsize=9, frameon=False)
    fig.supxlabel("averaging interval T (s)")
    fig.supylabel("coherence factor C(T)")
    return fig


def uv_figure(data: GridData, res: CoherenceResult, records: List[dict], step_s: float = 60.0):
    """(u,v) tracks coloured by C_after / C_before at the metric interval."""
    from matplotlib import colors as mcolors

    before = res.columns[0]
    later = res.columns[1:] or res.columns[:1]
    fig, axes = new_figure(len(later), ncols=min(2, len(later)), panel_size=(5.5, 5.0))
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
