"""``hitops.diagnose.diagnose``: the Python face of ``hitops diagnose``.

Same parameter names and defaults as hitops/schemas/diagnose.yml.  Reads the
compared columns, computes C(T) on the interval grid and at ``interval``,
tau_c, ranked comparisons and per-antenna summaries, writes the fixed-name
files into ``outdir`` and the requested plots into ``outdir/plots``, and
returns the summary as a dict (the content of ``summary.json``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ..errors import InputError
from ..io import flag_versions
from ..io.msv4.store import is_zarr_store
from . import tables
from .metrics import compute_coherence, parse_intervals, run_lengths
from .read import check_ms, read_grid
from .spectral import SPECTRAL_CSV, spectral_coherence, summary_section
from .spectral import render_text as spectral_text, write_csv as spectral_csv
from ..io.metadata import read_metadata
from .spectral_read import band_average, read_spectral, spectral

log = logging.getLogger("hitops.diagnose")

METRICS = ("coherence-factor", "coherence-time")
PLOTS = ("phase", "coherence", "uv", "waterfall", "spectrum")
#: plots that need several channels
SPECTRAL_PLOTS = ("waterfall", "spectrum")
PLOT_DIR = "plots"


def _split(text) -> list:
    if text is None:
        return []
    if isinstance(text, (list, tuple)):
        return [str(t).strip() for t in text if str(t).strip()]
    return [t.strip() for t in str(text).split(",") if t.strip()]


def _time_range(text):
    items = _split(text)
    if not items:
        return None
    try:
        lo, hi = (float(x) for x in items)
    except ValueError:
        raise InputError(f"--plot-time-range '{text}': give START,END in seconds from the "
                         "first sample, e.g. 0,2400") from None
    if not hi > lo:
        raise InputError(f"--plot-time-range '{text}': END must be larger than START")
    return lo, hi


def diagnose(ms, columns="DATA,CORRECTED_DATA", metric="coherence-factor", interval=60.0,
             intervals="log:1:3600:30", min_fill=0.5, ref_ms=None, ref_column="DATA",
             outdir="hitops-diagnose", plots=None, plot_time_range=None, baselines=None,
             correlations=None, calibrate_report=None, restore_flags=None) -> dict:
    """Coherence diagnostics of ``columns`` of ``ms``; see docs/diagnose.md.

    Returns the summary dict also written to ``outdir/summary.json``.  With
    ``outdir=None`` nothing is written (and no plots are made).
    """
    t_start = time.perf_counter()
    cols = list(dict.fromkeys(_split(columns)))
    if not cols:
        raise InputError("--columns is empty; give e.g. DATA,CORRECTED_DATA,PWC_DATA")
    if metric not in METRICS:
        raise InputError(f"--metric '{metric}' unknown; choose {' or '.join(METRICS)}")
    plot_kinds = [p.lower() for p in _split(plots)]
    bad = [p for p in plot_kinds if p not in PLOTS]
    if bad:
        raise InputError(f"--plots: unknown plot(s) {', '.join(bad)}; choose from "
                         f"{','.join(PLOTS)}")
    if plot_kinds and outdir is None:
        raise InputError("plots need an output directory (--outdir)")
    try:
        interval = float(interval)
        min_fill = float(min_fill)
    except (TypeError, ValueError):
        raise InputError(f"--interval {interval!r} / --min-fill {min_fill!r}: not numbers") \
            from None
    if not interval > 0:
        raise InputError(f"--interval {interval}: must be a positive number of seconds")
    if not 0 < min_fill <= 1:
        raise InputError(f"--min-fill {min_fill}: must lie in (0, 1]")
    grid = parse_intervals(intervals)
    trange = _time_range(plot_time_range)
    versions = flag_versions.split_names(restore_flags)
    if versions and is_zarr_store(Path(str(ms))):
        raise InputError(f"--restore-flags: {ms} is an MSv4 processing set, which keeps no CASA "
                         "flag versions (each data group has its own flags, never rewritten); "
                         "leave --restore-flags out")
    if versions:   # every version read and checked before FLAG is written
        flag_versions.restore_versions(str(ms), versions)

    spectral_grid = None
    check_ms(str(ms))   # a clear line for a path that is not a set, before any open
    meta = read_metadata(str(ms))   # the set's subtables, once for the run
    if spectral(meta):
        spectral_grid = read_spectral(str(ms), cols, correlations=correlations,
                                      baselines=baselines, want_uvw="uv" in plot_kinds,
                                      meta=meta)
        data = band_average(spectral_grid)
    else:
        data = read_grid(str(ms), cols, correlations=correlations, baselines=baselines,
                         want_uvw="uv" in plot_kinds, meta=meta)
    warnings = list(data.warnings)
    if spectral_grid is None and set(plot_kinds) & set(SPECTRAL_PLOTS):
        warnings.append(f"{ms} has one channel in one spectral window: no waterfall or "
                        "spectrum plot (they show phase and coherence across channels)")
        plot_kinds = [k for k in plot_kinds if k not in SPECTRAL_PLOTS]
    t_read = time.perf_counter()
    log.info("read %s: %d baselines x %d times x %d correlations, %d column(s) in %.1f s",
             ms, data.n_bl, data.n_time, len(data.corr_names), len(cols), t_read - t_start)

    longest = run_lengths(data.times, data.scan, data.dt)
    longest_all = float(longest.max(initial=0.0))
    if longest_all <= 0:
        raise InputError(f"{ms}: the selected baselines have no rows")
    if interval > longest_all:
        raise InputError(f"--interval {interval:g} s is longer than the track: the longest "
                         f"scan of the selected baselines lasts {longest_all:g} s; choose "
                         f"T <= {longest_all:g} s")
    too_long = grid[grid > longest_all]
    if too_long.size:
        warnings.append(f"intervals {', '.join(f'{t:g}' for t in too_long)} s are longer than "
                        f"the longest scan ({longest_all:g} s) and were left out of the C(T) "
                        "grid")
        grid = grid[grid <= longest_all]
    too_short = grid[grid < data.dt * (1 - 1e-9)]
    if too_short.size:
        # one sample per segment: C = 1 by definition, nothing to learn
        warnings.append(f"intervals {', '.join(f'{t:g}' for t in too_short)} s are shorter "
                        f"than the sampling interval ({data.dt:g} s) and were left out of the "
                        "C(T) grid")
        grid = grid[grid >= data.dt * (1 - 1e-9)]
    if interval < data.dt:
        warnings.append(f"--interval {interval:g} s is shorter than the sampling interval "
                        f"{data.dt:g} s: every segment holds one sample, so C = 1")

    res = compute_coherence(data.vis_stack, cols, data.flag, data.times, data.scan, data.dt,
                            grid, interval, min_fill=min_fill, corr_names=data.corr_names)
    spectral_res = (spectral_coherence(spectral_grid, interval, min_fill)
                    if spectral_grid is not None else None)
    t_coh = time.perf_counter()

    names = data.baseline_names
    records = tables.baseline_records(res, names, data.antenna_names, data.ant1, data.ant2,
                                      min_fill, data.dt)
    for col in cols:
        if sum(rec["columns"][col]["n_usable"] for rec in records) == 0:
            warnings.append(f"column {col} has no usable sample on any selected baseline "
                            "(all flagged, zero or not finite): its comparisons are undefined")
    if all(sum(rec["columns"][c]["n_usable"] for rec in records) == 0 for c in cols):
        raise InputError(f"{ms}: every sample of the selected baselines and correlations is "
                         "flagged, zero or not finite in every column; nothing to diagnose")
    dead = [rec["baseline"] for rec in records
            if all(rec["columns"][c]["n_usable"] == 0 for c in cols)]
    if dead:
        warnings.append(f"baseline(s) {', '.join(dead)} fully flagged in every column")

    comparisons = [tables.compare(records, cols[i], cols[j], metric, data.antenna_names,
                                  intervals=[float(t) for t in res.intervals])
                   for i in range(len(cols)) for j in range(i + 1, len(cols))]
    if len(cols) == 1:
        warnings.append("only one column given: no comparison table (give two or more "
                        "--columns, the first being 'before')")

    from . import confidence
    tracking, twarn = confidence.load(str(ms), calibrate_report)
    warnings += twarn
    confidence.annotate(comparisons, tracking)
    if tracking is not None:
        log.info("wrap-tracking confidence from %s (tracker %s)", tracking["path"],
                 tracking["tracker"])

    summary = {
        "tracking": tracking,
        "ms": str(ms), "columns": cols, "metric": metric, "interval_s": float(interval),
        "intervals_s": [float(t) for t in res.intervals],
        "metric_interval_index": res.k_interval,
        "correlations": data.corr_names, "sampling_interval_s": data.dt,
        "min_fill": min_fill, "antennas": data.antenna_names,
        "baselines": records, "comparisons": comparisons, "warnings": warnings,
        "ref_ms": str(ref_ms) if ref_ms else None, "reference_wraps": None,
        "outputs": {}, "timing_s": {},
        "spectral": summary_section(spectral_res) if spectral_res is not None else None,
    }

    wraps = None
    if ref_ms:
        from .wraps import reference_wraps
        wraps, wwarn = reference_wraps(str(ref_ms), data, ref_column or "DATA")
        warnings += wwarn
        summary["reference_wraps"] = {bl: {corr: int(t.size) for corr, t in per.items()}
                                      for bl, per in wraps.items()}

    for w in warnings:
        log.warning("%s", w)

    if outdir is not None:
        out = Path(outdir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"summary_json": out / tables.SUMMARY_JSON,
                 "table_csv": out / tables.TABLE_CSV,
                 "table_txt": out / tables.TABLE_TXT,
                 "antenna_csv": out / tables.ANTENNA_CSV}
        summary["outputs"] = {k: str(v) for k, v in paths.items()}
        summary["outputs"]["plots"] = []
        if plot_kinds:
            summary["outputs"]["plots"] = [str(p) for p in _make_plots(
                plot_kinds, data, res, records, cols, wraps, trange, out / PLOT_DIR,
                ref_ms)]
        if spectral_res is not None:
            paths["spectral_csv"] = out / SPECTRAL_CSV
            summary["outputs"]["spectral_csv"] = str(paths["spectral_csv"])
            spectral_csv(paths["spectral_csv"], spectral_res)
            summary["outputs"]["plots"] += [str(p) for p in _spectral_plots(
                plot_kinds, spectral_grid, spectral_res, cols, out / PLOT_DIR)]
        summary["timing_s"] = {"read": t_read - t_start, "coherence": t_coh - t_read,
                               "total": time.perf_counter() - t_start}
        tables.write_csv(paths["table_csv"], comparisons)
        tables.write_antenna_csv(paths["antenna_csv"], comparisons)
        paths["table_txt"].write_text(tables.render_text(summary) + (
            spectral_text(summary["spectral"]) if spectral_res is not None else ""))
        tables.write_json(paths["summary_json"], summary)
        log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    else:
        summary["timing_s"] = {"read": t_read - t_start, "coherence": t_coh - t_read,
                               "total": time.perf_counter() - t_start}
    for comp in comparisons:
        if comp["n_defined"]:
            log.info("%s vs %s: mean improvement %+.1f%%, median %+.1f%% (%d baselines)",
                     comp["after"], comp["before"], comp["mean_improvement_pct"],
                     comp["median_improvement_pct"], comp["n_defined"])
    return summary


def _make_plots(kinds, data, res, records, cols, wraps, trange, plot_dir: Path, ref_ms):
    from . import plots as P

    written = []
    names = data.baseline_names
    ref_label = Path(str(ref_ms)).name if ref_ms else "reference"
    if "phase" in kinds:
        for b, name in enumerate(names):
            fig = P.phase_figure(data, b, cols, wrap_times=(wraps or {}).get(name),
                                 time_range=trange, ref_label=ref_label)
            written.append(P.save(fig, plot_dir / f"phase-{name}.png"))
    if "coherence" in kinds:
        for b, name in enumerate(names):
            written.append(P.save(P.coherence_figure(res, b, name, records),
                                  plot_dir / f"coherence-{name}.png"))
        written.append(P.save(P.coherence_overview(res, names), plot_dir / "coherence-all.png"))
    if "uv" in kinds:
        written.append(P.save(P.uv_figure(data, res, records), plot_dir / "uv-coverage.png"))
    return written


def _spectral_plots(kinds, grid, res, cols, plot_dir: Path):
    from . import plots as P
    from . import spectral_plots as SP

    written = []
    if "waterfall" in kinds:
        for b, name in enumerate(grid.baseline_names):
            written.append(P.save(SP.waterfall_figure(grid, b, cols, res),
                                  plot_dir / f"waterfall-{name}.png"))
    if "spectrum" in kinds:
        written.append(P.save(SP.spectrum_figure(res), plot_dir / "coherence-spectrum.png"))
    return written
