"""Per-baseline metrics, ranked comparisons, array and per-antenna summaries, and their files.

Every compared pair of columns (each later column against each earlier one,
so DATA -> CORRECTED_DATA, DATA -> PWC_DATA and CORRECTED_DATA -> PWC_DATA
for three columns) gets a table ranked from the worst to the best
percentage improvement 100 * (after / before - 1).  A baseline whose value
cannot be computed keeps its row, ranked last, with a note saying why:
values are never silently NaN.  JSON holds ``null`` where a number is
undefined, always next to a note.
"""

from __future__ import annotations

import csv
import json
import math
from typing import Dict, List, Optional

import numpy as np

from .metrics import CoherenceResult, coherence_time

#: output file names inside --outdir (also listed in hitops/schemas/diagnose.yml)
SUMMARY_JSON = "summary.json"
TABLE_CSV = "coherence-table.csv"
TABLE_TXT = "coherence-table.txt"
ANTENNA_CSV = "antenna-table.csv"

METRIC_LABEL = {"coherence-factor": "coherence factor C(T)",
                "coherence-time": "effective coherence time tau_c (s)"}


def _num(x) -> Optional[float]:
    """Plain float for JSON, or None for NaN/inf."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _fmt_t(t: float) -> str:
    return f"{t:g}"


def baseline_records(res: CoherenceResult, baseline_names: List[str], ant_names: List[str],
                     ant1: np.ndarray, ant2: np.ndarray, min_fill: float, dt: float) -> List[dict]:
    """One record per baseline: every column's C(T), curve, tau_c and notes."""
    records = []
    k = res.k_interval
    for b, name in enumerate(baseline_names):
        rec = {"baseline": name, "ant1": ant_names[ant1[b]], "ant2": ant_names[ant2[b]],
               "longest_scan_s": _num(res.longest_run[b]), "columns": {}, "notes": []}
        for col in res.columns:
            n_usable = res.n_usable[col][b]
            curve = res.curve(col)[b]
            err = res.curve_err(col)[b]
            tau, bound = coherence_time(res.intervals, curve)
            per_corr = {}
            for c, corr in enumerate(res.corr_names):
                cc = res.c_mean[col][b, c]
                per_corr[corr] = {"coherence_factor": _num(cc[k]),
                                  "n_usable": int(n_usable[c]),
                                  "curve": [_num(v) for v in cc]}
            entry = {"coherence_factor": _num(curve[k]),
                     "coherence_factor_err": _num(err[k]),
                     "n_segments": int(res.n_segments[col][b, :, k].max(initial=0)),
                     "n_usable": int(n_usable.sum()),
                     "tau_c_s": _num(tau) if bound else None,
                     "tau_c_bound": bound or None,
                     "curve": [_num(v) for v in curve],
                     "curve_err": [_num(v) for v in err],
                     "per_correlation": per_corr,
                     "notes": [], "tau_note": None}
            if n_usable.sum() == 0:
                entry["notes"].append(f"{col}: no usable sample (all flagged, zero or not finite)")
            else:
                dead = [corr for c, corr in enumerate(res.corr_names) if n_usable[c] == 0]
                if dead:
                    entry["notes"].append(f"{col}: correlation(s) {','.join(dead)} have no "
                                          "usable sample; mean over the others")
                if not math.isfinite(curve[k]):
                    entry["notes"].append(
                        f"{col}: no segment of T={_fmt_t(res.interval)} s has >= "
                        f"{100 * min_fill:.0f}% usable samples (longest scan on this baseline "
                        f"{res.longest_run[b]:g} s)")
            if bound == ">":
                entry["tau_note"] = (f"{col}: C(T) stays above 1/e up to T={tau:g} s; "
                                      f"tau_c > {tau:g} s (lower bound)")
            elif bound == "<":
                entry["tau_note"] = (f"{col}: C(T) is below 1/e already at T={tau:g} s; "
                                      f"tau_c < {tau:g} s (upper bound)")
            rec["columns"][col] = entry
            rec["notes"] += entry["notes"]
        records.append(rec)
    return records


def metric_value(entry: dict, metric: str):
    """(value, bound) of a column entry for the chosen metric; value None when undefined."""
    if metric == "coherence-time":
        return entry["tau_c_s"], entry["tau_c_bound"] or ""
    return entry["coherence_factor"], "=" if entry["coherence_factor"] is not None else ""


def improvement(before, b_bound: str, after, a_bound: str):
    """Percentage improvement and its bound ('=', '>', '<'), or (None, reason)."""
    if before is None or after is None:
        return None, "undefined"
    if before <= 0:
        return None, "before is zero"
    pct = 100.0 * (after / before - 1.0)
    # after >= value and before <= value both push the ratio up: a lower bound
    up = {a_bound == ">", b_bound == "<"}
    down = {a_bound == "<", b_bound == ">"}
    if True in up and True in down:
        return None, "bounds in opposite directions"
    if True in up:
        return pct, ">"
    if True in down:
        return pct, "<"
    return pct, "="


def _stats(values: List[float]) -> Dict[str, Optional[float]]:
    if not values:
        return {"mean": None, "median": None, "min": None, "max": None}
    arr = np.asarray(values)
    return {"mean": float(arr.mean()), "median": float(np.median(arr)),
            "min": float(arr.min()), "max": float(arr.max())}


def compare(records: List[dict], before: str, after: str, metric: str,
            ant_names: List[str], intervals: Optional[List[float]] = None) -> dict:
    """Ranked table, array statistics and per-antenna summary of one column pair.

    Each row also lists ``worse_at_s``: the grid intervals T at which the
    "after" column's C(T) is below the "before" column's (the paper's claim
    "PWC beats FF+SC at every averaging interval on all baselines" holds when
    every list is empty).
    """
    rows = []
    for rec in records:
        worse = []
        if intervals is not None:
            for t, cb, ca in zip(intervals, rec["columns"][before]["curve"],
                                 rec["columns"][after]["curve"]):
                if cb is not None and ca is not None and ca < cb:
                    worse.append(float(t))
        b_val, b_bound = metric_value(rec["columns"][before], metric)
        a_val, a_bound = metric_value(rec["columns"][after], metric)
        pct, bound = improvement(b_val, b_bound, a_val, a_bound)
        notes = rec["columns"][before]["notes"] + rec["columns"][after]["notes"]
        if metric == "coherence-time":
            notes = notes + [n for n in (rec["columns"][before]["tau_note"],
                                         rec["columns"][after]["tau_note"]) if n]
        if pct is None and not notes:
            notes = [f"improvement undefined ({bound})"]
        rows.append({"baseline": rec["baseline"], "ant1": rec["ant1"], "ant2": rec["ant2"],
                     "before": b_val, "before_bound": b_bound or None,
                     "after": a_val, "after_bound": a_bound or None,
                     "improvement_pct": _num(pct),
                     "improvement_bound": bound if pct is not None else None,
                     "worse_at_s": worse,
                     "note": "; ".join(notes)})
    defined = [r for r in rows if r["improvement_pct"] is not None]
    undefined = [r for r in rows if r["improvement_pct"] is None]
    defined.sort(key=lambda r: (r["improvement_pct"], r["baseline"]))
    ranking = defined + undefined
    for i, r in enumerate(ranking):
        r["rank"] = i + 1
    pcts = [r["improvement_pct"] for r in defined]
    stats = _stats(pcts)
    n_lower = sum(r["improvement_bound"] == ">" for r in defined)
    n_upper = sum(r["improvement_bound"] == "<" for r in defined)
    summary = {
        "before": before, "after": after, "metric": metric,
        "ranking": ranking,
        "n_baselines": len(rows), "n_defined": len(defined),
        "n_undefined": len(undefined),
        "n_improved": sum(p > 0 for p in pcts),
        "n_worse_at_some_interval": sum(bool(r["worse_at_s"]) for r in rows),
        "n_lower_bounds": n_lower, "n_upper_bounds": n_upper,
        "mean_improvement_pct": stats["mean"], "median_improvement_pct": stats["median"],
        "min_improvement_pct": stats["min"], "max_improvement_pct": stats["max"],
        "worst_baseline": defined[0]["baseline"] if defined else None,
        "best_baseline": defined[-1]["baseline"] if defined else None,
        "antennas": antenna_summary(defined, ant_names, stats["median"], pcts),
    }
    return summary


def antenna_summary(defined_rows: List[dict], ant_names: List[str], array_median,
                    pcts: List[float]) -> List[dict]:
    """Per-antenna statistics of the improvement, worst antenna first.

    An antenna is marked ``outlier`` when the median improvement of its
    baselines lies more than 3 robust standard deviations (1.4826 * MAD of
    all baselines' improvements) below the array median, so one bad station
    stands out.
    """
    if pcts:
        arr = np.asarray(pcts)
        mad = float(np.median(np.abs(arr - np.median(arr)))) * 1.4826
    else:
        mad = 0.0
    out = []
    for name in ant_names:
        mine = [r for r in defined_rows if name in (r["ant1"], r["ant2"])]
        if not mine:
            continue
        vals = [r["improvement_pct"] for r in mine]
        worst = min(mine, key=lambda r: r["improvement_pct"])
        befores = [r["before"] for r in mine if r["before"] is not None]
        afters = [r["after"] for r in mine if r["after"] is not None]
        median = float(np.median(vals))
        z = (median - array_median) / mad if mad > 0 else 0.0
        out.append({"antenna": name, "n_baselines": len(mine),
                    "mean_improvement_pct": float(np.mean(vals)),
                    "median_improvement_pct": median,
                    "mean_before": _num(np.mean(befores)) if befores else None,
                    "mean_after": _num(np.mean(afters)) if afters else None,
                    "worst_baseline": worst["baseline"],
                    "worst_improvement_pct": worst["improvement_pct"],
                    "robust_z": float(z), "outlier": bool(z < -3.0)})
    out.sort(key=lambda a: (a["median_improvement_pct"], a["antenna"]))
    return out


# --------------------------------------------------------------------------- files

def _cell(value, bound=None, digits=4) -> str:
    if value is None:
        return "n/a"
    prefix = bound if bound in (">", "<") else ""
    return f"{prefix}{value:.{digits}f}"


#: wrap-tracking confidence columns (from hitops calibrate's report; empty without one)
TRACKING_FIELDS = ["suspected_slips", "bridged_gaps", "segments", "long_gap_segments", "jumps"]


def _predicted_cells(entry) -> dict:
    """calibrate's verdict for the baseline (empty without a report that has one)."""
    if not entry:
        return {"predicted_pct": "", "verdict": ""}
    return {"predicted_pct": round(entry["predicted_pct"], 2), "verdict": entry["verdict"]}


def _tracking_cells(entry) -> dict:
    return {k: ("" if not entry else entry.get(k, "")) for k in TRACKING_FIELDS}


def write_csv(path, comparisons: List[dict]) -> None:
    fields = ["comparison", "rank", "baseline", "ant1", "ant2", "metric", "before_column",
              "after_column", "before", "before_bound", "after", "after_bound",
              "improvement_pct", "improvement_bound", "n_intervals_worse", "note"]
    fields += TRACKING_FIELDS + ["predicted_pct", "verdict"]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for comp in comparisons:
            label = f"{comp['after']} vs {comp['before']}"
            for r in comp["ranking"]:
                writer.writerow({
                    "comparison": label, "rank": r["rank"], "baseline": r["baseline"],
                    "ant1": r["ant1"], "ant2": r["ant2"], "metric": comp["metric"],
                    "before_column": comp["before"], "after_column": comp["after"],
                    "before": "" if r["before"] is None else f"{r['before']:.6g}",
                    "before_bound": r["before_bound"] or "",
                    "after": "" if r["after"] is None else f"{r['after']:.6g}",
                    "after_bound": r["after_bound"] or "",
                    "improvement_pct": ("" if r["improvement_pct"] is None
                                        else f"{r['improvement_pct']:.4f}"),
                    "improvement_bound": r["improvement_bound"] or "",
                    "n_intervals_worse": len(r["worse_at_s"]),
                    "note": r["note"], **_tracking_cells(r.get("tracking")),
                    **_predicted_cells(r.get("predicted"))})


def write_antenna_csv(path, comparisons: List[dict]) -> None:
    fields = ["comparison", "antenna", "n_baselines", "mean_improvement_pct",
              "median_improvement_pct", "mean_before", "mean_after", "worst_baseline",
              "worst_improvement_pct", "robust_z", "outlier"]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields + TRACKING_FIELDS)
        writer.writeheader()
        for comp in comparisons:
            for a in comp["antennas"]:
                row = {k: a[k] for k in fields[1:]}
                row.update(_tracking_cells(a.get("tracking")))
                row["comparison"] = f"{comp['after']} vs {comp['before']}"
                writer.writerow(row)


def render_text(summary: dict) -> str:
    """The human-readable report: ranked tables, array statistics, antennas, warnings."""
    metric = summary["metric"]
    digits = 4 if metric == "coherence-factor" else 1
    lines = [f"HITOPS diagnose: {summary['ms']}",
             f"metric: {METRIC_LABEL[metric]}"
             + (f" at T = {summary['interval_s']:g} s" if metric == "coherence-factor" else
                f" from C(T) on {len(summary['intervals_s'])} intervals "
                f"{summary['intervals_s'][0]:g}-{summary['intervals_s'][-1]:g} s"),
             f"correlations: {','.join(summary['correlations'])} (per-baseline value = mean "
             f"over correlations); sampling interval {summary['sampling_interval_s']:g} s; "
             f"segments kept when >= {100 * summary['min_fill']:.0f}% filled",
             ""]
    if summary.get("tracking") is not None:
        lines.append(f"wrap tracking ({summary['tracking']['tracker']}, from "
                     f"{summary['tracking']['path']}): 'tracking' = suspected slips / bridged "
                     "gaps / segments / jumps of the reference-band wrap count")
        if summary["tracking"].get("verdict"):
            lines.append("'predicted' = hitops calibrate's verdict: the change of the coherence "
                         "factor that FPT was expected to make, before it ran (docs/calibrate.md)")
        lines.append("")
    if summary["warnings"]:
        lines.append("WARNINGS")
        lines += [f"  - {w}" for w in summary["warnings"]]
        lines.append("")
    for comp in summary["comparisons"]:
        before, after = comp["before"], comp["after"]
        width = max(12, len(before) + 2, len(after) + 2)
        lines.append(f"== {after} against {before}: baselines ranked from worst to best "
                     "improvement")
        track = summary.get("tracking") is not None
        predicted = any(r.get("predicted") for r in comp["ranking"])
        lines.append(f"{'rank':>4}  {'baseline':<10} {before:>{width}} {after:>{width}} "
                     f"{'improvement':>12}  "
                     + (f"{'predicted':>17}  " if predicted else "")
                     + (f"{'tracking':>12}  " if track else "") + "note")
        for r in comp["ranking"]:
            pct = r["improvement_pct"]
            pct_s = "n/a" if pct is None else (
                (r["improvement_bound"] if r["improvement_bound"] in (">", "<") else "")
                + f"{pct:+.1f}%")
            lines.append(f"{r['rank']:>4}  {r['baseline']:<10} "
                         f"{_cell(r['before'], r['before_bound'], digits):>{width}} "
                         f"{_cell(r['after'], r['after_bound'], digits):>{width}} "
                         f"{pct_s:>12}  "
                         + (f"{_predicted_text(r.get('predicted')):>17}  " if predicted else "")
                         + (f"{_track_cell(r.get('tracking')):>12}  " if track else "")
                         + r["note"])
        if comp["n_defined"]:
            extra = ""
            if comp["n_lower_bounds"] or comp["n_upper_bounds"]:
                extra = (f" (includes {comp['n_lower_bounds']} lower and "
                         f"{comp['n_upper_bounds']} upper bounds)")
            # every value a lower (upper) bound makes mean and median bounds too
            pre = (">" if comp["n_lower_bounds"] == comp["n_defined"] else
                   "<" if comp["n_upper_bounds"] == comp["n_defined"] else "")
            lines.append(f"array: mean improvement {pre}{comp['mean_improvement_pct']:+.1f}%, "
                         f"median {pre}{comp['median_improvement_pct']:+.1f}%, range "
                         f"{comp['min_improvement_pct']:+.1f}% ({comp['worst_baseline']}) to "
                         f"{comp['max_improvement_pct']:+.1f}% ({comp['best_baseline']}); "
                         f"{comp['n_improved']}/{comp['n_defined']} baselines improved{extra}")
        else:
            lines.append("array: no baseline has a defined improvement (see notes)")
        if comp["n_undefined"]:
            lines.append(f"       {comp['n_undefined']} baseline(s) undefined, listed last")
        worse = [r for r in comp["ranking"] if r["worse_at_s"]]
        if worse:
            lines.append(f"       {after} has lower C(T) than {before} at some interval on "
                         f"{len(worse)} baseline(s): " + ", ".join(
                             f"{r['baseline']} (T={','.join(f'{t:.3g}' for t in r['worse_at_s'][:4])}"
                             f"{',...' if len(r['worse_at_s']) > 4 else ''} s)" for r in worse[:8])
                         + (", ..." if len(worse) > 8 else ""))
        else:
            lines.append(f"       {after} has C(T) >= {before} at every interval on every "
                         "baseline with data")
        lines.append("per antenna (worst first):")
        lines.append(f"  {'antenna':<8} {'n_bl':>4} {'median':>9} {'mean':>9}  "
                     + (f"{'tracking':>12}  " if track else "") + "worst baseline")
        for a in comp["antennas"]:
            mark = "  <-- outlier" if a["outlier"] else ""
            lines.append(f"  {a['antenna']:<8} {a['n_baselines']:>4} "
                         f"{a['median_improvement_pct']:>+8.1f}% {a['mean_improvement_pct']:>+8.1f}%  "
                         + (f"{_track_cell(a.get('tracking')):>12}  " if track else "")
                         + f"{a['worst_baseline']} ({a['worst_improvement_pct']:+.1f}%){mark}")
        lines.append("")
    return "\n".join(lines) + "\n"


def _predicted_text(entry) -> str:
    return "-" if not entry else f"{entry['predicted_pct']:+.1f}% ({entry['verdict']})"


def _track_cell(entry) -> str:
    from .confidence import cell
    return cell(entry)


def write_json(path, summary: dict) -> None:
    with open(path, "w") as fh:
        json.dump(summary, fh, indent=1, allow_nan=False)
        fh.write("\n")
