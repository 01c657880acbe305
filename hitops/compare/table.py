"""Build, write and summarise the peak-flux recovery table."""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from ..errors import InputError, OutputExistsError

log = logging.getLogger("hitops.compare")

#: The FPT paper's simulation results (Simelane, Kemball & Deane, "Frequency Phase
#: Transfer for Future Millimetre Arrays with Arbitrary Frequency Ratios",
#: arXiv:2606.27143, section Results).
PAPER = {
    "recovery": {"pwc": (0.965, 0.0046), "ffsc": (0.868, 0.0045)},
    "coherence": {
        "ffsc_range": (0.61, 0.96),
        "pwc_range": (0.88, 0.99),
        "pwc_over_ffsc_mean_pct": 18.0,
        "pwc_over_ffsc_median_pct": 11.0,
        "pwc_over_ffsc_range_pct": (3.0, 50.0),
        "pwc_beats_ffsc_on_every_baseline": True,
    },
}

#: Display names of the usual labels.
METHOD_NAMES = {"raw": "raw (DATA)", "ffsc": "FF+SC (CORRECTED_DATA)",
                "cfpt": "CFPT (CFPT_DATA)", "pwc": "PWC (PWC_DATA)",
                "pwcnc": "PWC, no control (PWC_NC_DATA)",
                "pwcwin": "PWC, one ratio per window (PWC_WIN_DATA)",
                "pwcft": "PWC from the fringe-fit table (applycal)"}


def recovery(peak: float, peak_err: float, input_peak: float,
             input_peak_err: float = 0.0) -> tuple:
    """Fractional recovery and its 1-sigma uncertainty (first-order propagation)."""
    if not (input_peak > 0 and math.isfinite(input_peak)):
        raise InputError(f"input peak {input_peak!r} must be a positive number of Jy/beam")
    if input_peak_err < 0:
        raise InputError(f"input peak error {input_peak_err!r} must not be negative")
    value = peak / input_peak
    rel = math.hypot(peak_err / peak if peak else math.inf, input_peak_err / input_peak)
    err = abs(value) * rel if peak else peak_err / input_peak
    return float(value), float(err)


def _split(text) -> List[str]:
    if text is None:
        return []
    if isinstance(text, (list, tuple)):
        return [str(t) for t in text]
    return [t.strip() for t in str(text).split(",") if t.strip()]


def _read_fit(path: str) -> Dict:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"imfit result '{path}' does not exist; run the imfit step "
                         "(hitops.casa.imfit with outfile=...) first")
    try:
        fit = json.loads(p.read_text())
    except json.JSONDecodeError as err:
        raise InputError(f"imfit result '{path}' is not JSON ({err})") from err
    if fit.get("method") == "no-source":
        return fit   # no peak, by design: the image holds no source above the noise
    for key in ("peak", "peak_err"):
        if not isinstance(fit.get(key), (int, float)) or not math.isfinite(fit[key]):
            raise InputError(f"imfit result '{path}' has no finite '{key}'")
    return fit


def build_rows(fit_files: Sequence[str], labels: Sequence[str], input_peak: float,
               input_peak_err: float = 0.0, reference: str = "none") -> List[Dict]:
    if labels and len(labels) != len(fit_files):
        raise InputError(f"{len(labels)} labels ({','.join(labels)}) for "
                         f"{len(fit_files)} fit files: give one label per file or none")
    rows = []
    for i, path in enumerate(fit_files):
        fit = _read_fit(path)
        label = labels[i] if labels else str(fit.get("label") or Path(path).stem)
        if fit.get("method") == "no-source":
            # no number for a fit to noise
            recovery(1.0, 0.0, input_peak, input_peak_err)   # still check the input peak
            value = err = peak = peak_err = None
        else:
            value, err = recovery(fit["peak"], fit["peak_err"], input_peak, input_peak_err)
            peak, peak_err = float(fit["peak"]), float(fit["peak_err"])
        row = {
            "label": label,
            "method": METHOD_NAMES.get(label, label),
            "image": fit.get("image", ""),
            "fit": fit.get("method", "gaussian"),
            "note": _fallback_note(fit),
            "peak_jy": peak,
            "peak_err_jy": peak_err,
            "input_peak_jy": float(input_peak),
            "recovery": value,
            "recovery_err": err,
        }
        if reference == "paper":
            ref = PAPER["recovery"].get(label)
            row["paper_recovery"] = ref[0] if ref else None
            row["paper_recovery_err"] = ref[1] if ref else None
        rows.append(row)
    labels_seen = [r["label"] for r in rows]
    duplicates = sorted({l for l in labels_seen if labels_seen.count(l) > 1})
    if duplicates:
        raise InputError(f"labels {duplicates} appear more than once; pass --labels")
    return rows


def _fallback_note(fit: Dict) -> str:
    """Why a row is not a Gaussian fit (empty for a fit)."""
    method = fit.get("method", "gaussian")
    if method == "gaussian":
        return ""
    if method == "no-source":
        snr = fit.get("snr")
        return ("no source: the best fit is only " + (f"{snr:.1f} x the image rms"
                                                       if isinstance(snr, (int, float))
                                                       else "at the noise level"))
    reason = str(fit.get("reason", ""))
    source = "dirty-image" if "dirty" in str(fit.get("fallback_image", "")) else "image"
    if fit.get("diverged", "diverged" in reason or "no finite" in reason):
        return f"max-pixel: CLEAN diverged, brightest {source} pixel"
    return f"max-pixel: fit did not converge, brightest {source} pixel"


def _pm(value, err, digits=4) -> str:
    if value is None:
        return "no source"
    return f"{value:.{digits}f} ± {err:.{digits}f}"


def _fmt(value, digits=4) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def markdown(rows: List[Dict], coherence: Optional[Dict], reference: str) -> str:
    out = ["# Fractional peak-flux recovery", "",
           "Fitted (CASA imfit) peak / input peak; uncertainty from the imfit peak error.", ""]
    header = ["method", "peak (Jy/beam)", "recovery"]
    if reference == "paper":
        header.append("paper")
    out.append("| " + " | ".join(header) + " |")
    out.append("|" + "---|" * len(header))
    for r in rows:
        note = f" ({r['note']})" if r.get("note") else ""
        cells = [r["method"] + note, _pm(r["peak_jy"], r["peak_err_jy"]),
                 _pm(r["recovery"], r["recovery_err"])]
        if reference == "paper":
            cells.append(f"{r['paper_recovery']:.3f} ± {r['paper_recovery_err']:.4f}"
                         if r.get("paper_recovery") is not None else "-")
        out.append("| " + " | ".join(cells) + " |")
    if coherence:
        measure = coherence.get("measure", "per channel")
        out += ["", "# Coherence of the residual phases (per baseline"
                + ("" if measure == "per channel" else f"; {measure}") + ")", ""]
        cols = coherence["columns"]
        out.append("| baseline | " + " | ".join(cols) + " | PWC vs FF+SC |")
        out.append("|" + "---|" * (len(cols) + 2))
        for bl in coherence["baselines"]:
            gain = bl.get("pwc_over_ffsc_pct")
            out.append(f"| {bl['baseline']} | " + " | ".join(_fmt(bl.get(c), 3) for c in cols)
                       + f" | {_fmt(gain, 1)}{'%' if gain is not None else ''} |")
        stats = coherence.get("stats", {})
        if stats:
            out += ["", "| statistic | ours | paper |", "|---|---|---|"]
            pc = PAPER["coherence"]
            paper = {
                "ffsc_min": pc["ffsc_range"][0], "ffsc_max": pc["ffsc_range"][1],
                "pwc_min": pc["pwc_range"][0], "pwc_max": pc["pwc_range"][1],
                "pwc_over_ffsc_mean_pct": pc["pwc_over_ffsc_mean_pct"],
                "pwc_over_ffsc_median_pct": pc["pwc_over_ffsc_median_pct"],
                "pwc_ge_ffsc_every_baseline": pc["pwc_beats_ffsc_on_every_baseline"],
            } if reference == "paper" else {}
            for key, value in stats.items():
                out.append(f"| {key} | {_fmt(value, 3)} | {_fmt(paper.get(key), 3)} |")
    return "\n".join(out) + "\n"


def coherence_summary(path: str) -> Dict:
    """Per-baseline coherence of each method from a `hitops diagnose` summary.json.

    Reads diagnose's ``{"baselines": [{"baseline": "AP-PV", "columns":
    {"DATA": {"coherence_factor": ..}, "PWC_DATA": {..}}}]}``; also accepts
    ``{"baselines": [{"baseline": "AP-PV", "coherence": {"raw": .., ...}}]}`` and
    ``{"coherence": {"AP-PV": {"DATA": .., ...}}}``; column names are mapped
    to raw/ffsc/cfpt/pwc where recognisable.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"diagnose summary '{path}' does not exist; run hitops diagnose first")
    data = json.loads(p.read_text())
    per_bl = _extract_per_baseline(data)
    all_channels = _all_channel_coherence(data)
    for name, values in all_channels.items():
        per_bl.setdefault(name, {}).update(values)
    if not per_bl:
        raise InputError(f"diagnose summary '{path}' has no per-baseline coherence values "
                         "this tool recognises")
    cols = []
    rows = []
    for name, values in per_bl.items():
        row = {"baseline": name}
        for key, value in values.items():
            label = _method_label(key)
            if label is None or not isinstance(value, (int, float)):
                continue
            row[label] = float(value)
            if label not in cols:
                cols.append(label)
        if row.get("ffsc") and row.get("pwc") is not None:
            row["pwc_over_ffsc_pct"] = 100.0 * (row["pwc"] / row["ffsc"] - 1.0)
        rows.append(row)
    order = [c for c in ("raw", "ffsc", "cfpt", "pwc") if c in cols] + \
        [c for c in cols if c not in ("raw", "ffsc", "cfpt", "pwc")]
    stats = {}
    if "ffsc" in order and "pwc" in order:
        import numpy as np

        ffsc = np.array([r["ffsc"] for r in rows if "ffsc" in r and "pwc" in r])
        pwc = np.array([r["pwc"] for r in rows if "ffsc" in r and "pwc" in r])
        gain = 100.0 * (pwc / ffsc - 1.0)
        stats = {
            "n_baselines": int(ffsc.size),
            "ffsc_min": float(ffsc.min()), "ffsc_max": float(ffsc.max()),
            "pwc_min": float(pwc.min()), "pwc_max": float(pwc.max()),
            "pwc_over_ffsc_mean_pct": float(gain.mean()),
            "pwc_over_ffsc_median_pct": float(np.median(gain)),
            "pwc_ge_ffsc_every_baseline": bool(np.all(pwc >= ffsc)),
        }
    return {"source": str(path), "interval_s": data.get("interval_s"), "columns": order,
            "baselines": rows, "stats": stats,
            "measure": "time and all channels averaged together" if all_channels else "per channel"}


def _all_channel_coherence(data) -> Dict[str, Dict]:
    """Per baseline and column, C over every channel of every window (time and channels
    averaged together), from a wideband `hitops diagnose` summary's ``spectral`` block;
    empty for a one-channel summary.

    This is the coherence a multi-frequency-synthesis image sees: it falls with a phase
    slope across the channels (one ratio per window applied to an excess path), which
    the per-channel ``coherence_factor`` does not see (docs/diagnose.md, "Wideband").
    """
    spectral = data.get("spectral") if isinstance(data, dict) else None
    columns = spectral.get("columns") if isinstance(spectral, dict) else None
    out: Dict[str, Dict] = {}
    for column, block in (columns or {}).items():
        for name, entry in (block.get("baselines") or {}).items():
            value = entry.get("all_channels") if isinstance(entry, dict) else None
            if isinstance(value, (int, float)):
                out.setdefault(str(name), {})[column] = float(value)
    return out


_ALIASES = {
    "raw": "raw", "data": "raw",
    "ffsc": "ffsc", "ff+sc": "ffsc", "corrected": "ffsc", "corrected_data": "ffsc",
    "cfpt": "cfpt", "cfpt_data": "cfpt",
    "pwc": "pwc", "pwc_data": "pwc",
    "pwcnc": "pwcnc", "pwc_nc_data": "pwcnc",
    "pwcwin": "pwcwin", "pwc_win_data": "pwcwin",
}


def _method_label(key: str) -> Optional[str]:
    return _ALIASES.get(str(key).strip().lower())


def _extract_per_baseline(data) -> Dict[str, Dict]:
    if isinstance(data, dict):
        if isinstance(data.get("baselines"), list):
            out = {}
            for entry in data["baselines"]:
                name = entry.get("baseline") or entry.get("name")
                values = entry.get("coherence", entry)
                if isinstance(entry.get("columns"), dict):
                    # hitops diagnose: {"columns": {"PWC_DATA": {"coherence_factor": ..}}}
                    values = {col: v.get("coherence_factor") for col, v in entry["columns"].items()
                              if isinstance(v, dict)}
                if name and isinstance(values, dict):
                    out[str(name)] = values
            if out:
                return out
        for key in ("coherence", "coherence_factor", "per_baseline"):
            block = data.get(key)
            if isinstance(block, dict) and block and all(isinstance(v, dict) for v in block.values()):
                return {str(k): v for k, v in block.items()}
    return {}


def compare(fits, labels=None, input_peak: float = 1.0, input_peak_err: float = 0.0,
            coherence: Optional[str] = None, reference: str = "none", *,
            outdir: str, name: str = "peak-flux", overwrite: bool = False) -> Dict:
    """Write {outdir}/{name}.csv/.md/.json; return the JSON payload."""
    fit_files = _split(fits)
    if not fit_files:
        raise InputError("no imfit result files given (FITS argument is empty)")
    if reference not in ("none", "paper"):
        raise InputError(f"reference '{reference}' must be 'none' or 'paper'")
    rows = build_rows(fit_files, _split(labels), float(input_peak), float(input_peak_err),
                      reference)
    coh = coherence_summary(coherence) if coherence else None
    out = Path(outdir)
    targets = {ext: out / f"{name}.{ext}" for ext in ("csv", "md", "json")}
    existing = [str(p) for p in targets.values() if p.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} exist; pass --overwrite to replace them")
    out.mkdir(parents=True, exist_ok=True)
    payload = {"rows": rows}
    if coh:
        payload["coherence"] = coh
    if reference == "paper":
        payload["paper"] = PAPER
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
    writer.writeheader()
    writer.writerows(rows)
    texts = {"csv": buf.getvalue(), "md": markdown(rows, coh, reference),
             "json": json.dumps(payload, indent=2) + "\n"}
    for ext, path in targets.items():
        tmp = path.with_name(path.name + ".partial")
        tmp.write_text(texts[ext])
        tmp.replace(path)
    for r in rows:
        log.info("%-24s recovery %s%s", r["method"], _pm(r["recovery"], r["recovery_err"]),
                 f" ({r['note']})" if r["note"] else "")
    log.info("wrote %s", ", ".join(str(p) for p in targets.values()))
    return payload


#: Short names of the methods for the terminal
SHORT_NAMES = {"raw": "raw", "ffsc": "FF+SC", "cfpt": "CFPT", "cwu": "CWU", "pwc": "PWC",
               "pwcnc": "PWC-NC", "pwcwin": "PWCwin"}


def text_summary(payload: Dict) -> str:
    """The comparison for a terminal: recovery per image, coherence per baseline, statistics.

    ``payload`` is what :func:`compare` returns (and writes as JSON).  About
    20 lines for the demo's 10 baselines; the markdown file has the same numbers.
    """
    rows = payload.get("rows", [])
    ref = payload.get("paper") is not None
    peak = rows[0]["input_peak_jy"] if rows else 1.0
    out = [f"Fractional peak-flux recovery (CASA imfit peak / the {peak:g} Jy/beam put in)"
           + ("; paper's value in brackets" if ref else "") + ":"]
    width = max((len(r["method"]) for r in rows), default=10)
    for r in rows:
        if r["recovery"] is None:
            cell = "no source"
        else:
            cell = f"{r['recovery']:.3f} ± {r['recovery_err']:.3f}"
        if ref and r.get("paper_recovery") is not None:
            cell += f"  [{r['paper_recovery']:.3f}]"
        note = r.get("note") or ""
        if note.startswith("max-pixel: CLEAN diverged"):
            note = "CLEAN diverged: brightest pixel of the dirty image"
        elif note.startswith("max-pixel"):
            note = "fit did not converge: brightest pixel of the dirty image"
        elif note.startswith("no source"):
            note = note[len("no source: "):] if note.startswith("no source: ") else ""
        out.append(f"  {r['method']:<{width}}  {cell:<15}" + (f"  ({note})" if note else ""))
    coh = payload.get("coherence")
    if coh and coh.get("baselines"):
        cols = coh["columns"]
        interval = coh.get("interval_s")
        title = f"Coherence C({interval:g} s)" if isinstance(interval, (int, float)) else "Coherence"
        if coh.get("measure", "per channel") != "per channel":
            title += f", {coh['measure']},"
        has_gain = any(b.get("pwc_over_ffsc_pct") is not None for b in coh["baselines"])
        names = [SHORT_NAMES.get(c, c) for c in cols]
        out += ["", f"{title} per baseline:",
                "  " + f"{'baseline':<9}" + "".join(f"{n:>7}" for n in names)
                + ("  PWC vs FF+SC" if has_gain else "")]
        for bl in coh["baselines"]:
            cells = "".join(f"{bl[c]:>7.3f}" if isinstance(bl.get(c), (int, float)) else f"{'-':>7}"
                            for c in cols)
            gain = bl.get("pwc_over_ffsc_pct")
            out.append(f"  {bl['baseline']:<9}{cells}"
                       + (f"  {gain:+11.1f}%" if gain is not None else ""))
        st = coh.get("stats") or {}
        if st:
            n = st.get("n_baselines")
            wins = ("on every baseline" if st.get("pwc_ge_ffsc_every_baseline")
                    else "not on every baseline")
            out.append(f"  PWC vs FF+SC: mean {st['pwc_over_ffsc_mean_pct']:+.1f}%, median "
                       f"{st['pwc_over_ffsc_median_pct']:+.1f}%; PWC >= FF+SC {wins} ({n})")
            if ref:
                pc = PAPER["coherence"]
                out.append(f"  ours:  FF+SC {st['ffsc_min']:.2f}-{st['ffsc_max']:.2f}, PWC "
                           f"{st['pwc_min']:.2f}-{st['pwc_max']:.2f}")
                out.append(f"  paper: FF+SC {pc['ffsc_range'][0]:.2f}-{pc['ffsc_range'][1]:.2f}, "
                           f"PWC {pc['pwc_range'][0]:.2f}-{pc['pwc_range'][1]:.2f}; PWC vs FF+SC "
                           f"mean +{pc['pwc_over_ffsc_mean_pct']:g}%, median "
                           f"+{pc['pwc_over_ffsc_median_pct']:g}%")
    return "\n".join(out) + "\n"
