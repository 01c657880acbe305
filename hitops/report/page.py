"""The run's page as one HTML file: inline CSS and script, relative links only.

It opens from file:// on an offline machine (no server, no network, no CDN).  The
answer comes first (peak-flux table and verdict), then the images, coherence,
stations, steps, flags and provenance.  Numbers are text, so they can be copied.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

from .collect import RunFacts
from .images import Picture
from .phaseref import phaseref_windows
from .provenance import Provenance
from .steps import StepLog

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#1d2330;background:#f6f7f9}
header{background:#14213d;color:#fff;padding:18px 32px}header h1{margin:0;font-size:22px}
header p{margin:4px 0 0;color:#cfd6e4;font-size:13px}
nav{background:#1f2f52;padding:6px 32px}nav a{color:#dfe6f3;margin-right:16px;font-size:13px;text-decoration:none}
main{padding:16px 32px;max-width:1400px}section{background:#fff;border:1px solid #dde2ea;border-radius:6px;padding:14px 20px;margin:14px 0}
h2{font-size:18px;margin:4px 0 10px;color:#14213d}h3{font-size:15px;margin:14px 0 6px}
table{border-collapse:collapse;font-size:13px;margin:6px 0}th,td{border-bottom:1px solid #e4e8ef;padding:4px 10px;text-align:right}
th{background:#eef1f6;cursor:default}th.sort{cursor:pointer}th.sort:after{content:' \\2195';color:#8a94a6}
td:first-child,th:first-child{text-align:left}table.left td:nth-child(-n+3),table.left th:nth-child(-n+3){text-align:left}td.l,th.l{text-align:left}
.verdict{font-size:17px;padding:10px 14px;background:#e9f5ee;border-left:5px solid #2e8b57;margin:8px 0}
.verdict.warn{background:#fff5e6;border-color:#d98c1f}
.grid{display:flex;flex-wrap:wrap;gap:12px}.card{border:1px solid #e0e4ea;border-radius:4px;padding:6px;background:#fff;width:380px}
.card img{width:100%;height:auto}.card p{font-size:12px;margin:4px 2px}.plots img{width:440px;border:1px solid #e0e4ea}
.muted{color:#6b7487;font-size:12px}code,pre{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12px}
pre{background:#f1f3f7;padding:8px;overflow-x:auto;white-space:pre-wrap}.bad{color:#b3261e}.good{color:#1e7b46}
details summary{cursor:pointer;font-weight:600;margin:6px 0}
"""

_SORT_JS = """
document.querySelectorAll('table.sortable').forEach(function(t){
  t.querySelectorAll('th').forEach(function(th,i){th.classList.add('sort');
    th.addEventListener('click',function(){
      var rows=Array.from(t.tBodies[0].rows), up=th.dataset.dir!=='up';
      t.querySelectorAll('th').forEach(function(h){delete h.dataset.dir});th.dataset.dir=up?'up':'down';
      rows.sort(function(a,b){var g=function(c){var s=c.querySelector('[data-v]');return c.dataset.v||(s&&s.dataset.v)||c.textContent};var x=g(a.cells[i]),y=g(b.cells[i]);
        var nx=parseFloat(x),ny=parseFloat(y);
        if(!isNaN(nx)&&!isNaN(ny)){return up?nx-ny:ny-nx}return up?x.localeCompare(y):y.localeCompare(x)});
      rows.forEach(function(r){t.tBodies[0].appendChild(r)});});});});
"""


def _e(text) -> str:
    return html.escape(str(text))


def _rel(path: Path, base: Path) -> str:
    return os.path.relpath(Path(path).resolve(), base.resolve()).replace(os.sep, "/")


def _num(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, float)):
        return f"{value:.{digits}f}" if isinstance(value, float) else str(value)
    return _e(value)


def _table(head: Sequence[str], rows: Iterable[Sequence], cls: str = "", ident: str = "") -> str:
    out = [f"<table class='{cls}'{f' id={ident!r}' if ident else ''}><thead><tr>"]
    out += [f"<th>{_e(h)}</th>" for h in head]
    out.append("</tr></thead><tbody>")
    for row in rows:
        cells = []
        for cell in row:
            if isinstance(cell, float):
                cells.append(f"<td data-v='{cell!r}'>{_num(cell)}</td>")
            else:
                cells.append(f"<td>{cell if isinstance(cell, _Raw) else _num(cell)}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


class _Raw(str):
    """Cell text that is already HTML."""


def verdict(facts: RunFacts) -> str:
    """The answer in one sentence."""
    rows = {r.label: r for r in facts.peak_rows}
    pwc, ffsc = rows.get("pwc"), rows.get("ffsc")
    if pwc and pwc.recovery is not None:
        text = (f"PWC recovers {pwc.recovery:.4f} ± {pwc.recovery_err or 0:.4f} of the input peak")
        if ffsc and ffsc.recovery is not None:
            diff = pwc.recovery - ffsc.recovery
            sigma = ((pwc.recovery_err or 0) ** 2 + (ffsc.recovery_err or 0) ** 2) ** 0.5
            word = "more" if diff > 0 else "less"
            text += (f", {abs(diff):.4f} {word} than FF+SC's {ffsc.recovery:.4f} ± "
                     f"{ffsc.recovery_err or 0:.4f}")
            if sigma > 0:
                text += f" ({abs(diff) / sigma:.0f} σ)"
        return text + "."
    if pwc:
        return f"PWC gave no peak: {pwc.note or pwc.fit}."
    if facts.diagnose:
        return "No images in this directory. " + _coherence_verdict(facts.diagnose)
    if facts.calibrate_reports:
        return "Calibration only: the per-station facts are below."
    return "Nothing this page knows how to show was found in the directory."


def _coherence_verdict(summary: Dict) -> str:
    """Median per-baseline coherence of each diagnosed column, in one sentence."""
    import statistics

    parts = []
    for col in summary.get("columns", []):
        values = [bl["columns"][col]["coherence_factor"] for bl in summary.get("baselines", [])
                  if isinstance(bl.get("columns", {}).get(col, {}).get("coherence_factor"), float)]
        if values:
            parts.append(f"{col} {statistics.median(values):.3f}")
    n_bl = len(summary.get("baselines", []))
    interval = summary.get("interval_s", 0.0)
    return (f"Median coherence C({interval:g} s) over {n_bl} baselines: " + ", ".join(parts) + "."
            if parts else "The coherence of each column is below.")


def _peak_section(facts: RunFacts) -> str:
    if not facts.peak_rows:
        return (f"<section id='answer'><h2>Answer</h2><div class='verdict warn' id='verdict'>"
                f"{_e(verdict(facts))}</div></section>")
    body = [(r.method, r.peak_jy, r.peak_err_jy, r.recovery, r.recovery_err,
             r.note or r.fit) for r in facts.peak_rows]
    cls = "verdict" if any(r.label == "pwc" and r.recovery for r in facts.peak_rows) else "verdict warn"
    table = _table(["method", "peak (Jy/beam)", "± (Jy/beam)", "recovery", "±", "fit"], body,
                   ident="peak-flux")
    peak = f" of the input peak {facts.input_peak} Jy/beam" if facts.input_peak else ""
    source = facts.peak_table.name if facts.peak_table else "peak-flux.json"
    return (f"<section id='answer'><h2>Fractional peak-flux recovery</h2>"
            f"<div class='{cls}' id='verdict'>{_e(verdict(facts))}</div>{table}"
            f"<p class='muted'>CASA imfit Gaussian peak{_e(peak)}; uncertainty from imfit. "
            f"Source: <a href='{source}'>{source}</a> (also .csv, .md).</p></section>")


def _images_section(pictures: List[Picture], base: Path) -> str:
    if not pictures:
        return ""
    cards = [f"<div class='card'><img src='{_rel(p.png, base)}' alt='{_e(p.label)} image'>"
             f"<p><b>{_e(p.label)}</b> ({_e(p.shown)}): {_e(p.caption)}</p>"
             f"<p><a href='{_rel(p.fits, base)}'>{_e(p.fits.name)}</a></p></div>" for p in pictures]
    return ("<section id='images'><h2>Images</h2><p class='muted'>One colour scale for the row "
            "(-0.1 to 1 x the input peak); the ellipse is the restoring beam, + the fitted peak."
            "</p><div class='grid'>" + "".join(cards) + "</div></section>")


def _coherence_section(facts: RunFacts, base: Path) -> str:
    summary = facts.diagnose
    if not summary:
        return ""
    cols = summary.get("columns", [])
    rows = []
    for bl in summary.get("baselines", []):
        row = [bl.get("baseline", "")]
        for col in cols:
            entry = bl.get("columns", {}).get(col, {})
            row.append(entry.get("coherence_factor"))
        for col in cols:
            entry = bl.get("columns", {}).get(col, {})
            tau = entry.get("tau_c_s")
            bound = str(entry.get("tau_c_bound") or "=")
            if isinstance(tau, (int, float)):   # a '>' bound: C never fell to 1/e
                text = f"{'' if bound == '=' else bound}{tau:.1f}"
                row.append(_Raw(f"<span data-v='{float(tau)!r}'>{_e(text)}</span>"))
            else:
                row.append(None)
        rows.append(row)
    head = (["baseline"] + [f"C({summary.get('interval_s', '?'):g} s) {c}" for c in cols]
            + [f"τc (s) {c}" for c in cols])
    plots = _spectral_table(summary.get("spectral")) + _plots(facts, base)
    rel = _rel(facts.diagnose_dir, base) if facts.diagnose_dir else "diagnose"
    return (f"<section id='coherence'><h2>Coherence per baseline</h2>"
            f"<p class='muted'>Click a heading to sort. From <a href='{rel}/summary.json'>"
            f"{rel}/summary.json</a> and <a href='{rel}/coherence-table.txt'>coherence-table.txt"
            f"</a>.</p>{_table(head, rows, 'sortable', 'coherence-table')}{plots}</section>")


def _spectral_table(spectral: Optional[Dict]) -> str:
    """Wideband sets: per baseline and column, C over all channels, per window and the
    worst channel of each window (diagnose's 'spectral' section)."""
    if not spectral:
        return ""
    windows = spectral.get("windows", [])
    names = [f"{w['freq_min_hz'] / 1e9:.2f}-{w['freq_max_hz'] / 1e9:.2f} GHz ({w['n_chan']} ch)"
             for w in windows]
    head = (["baseline", "column", "C all channels"] + [f"C window {n}" for n in names]
            + [f"worst channel {n}" for n in names])
    rows = []
    for col, entry in spectral.get("columns", {}).items():
        for bl, values in entry.get("baselines", {}).items():
            rows.append([bl, col, values.get("all_channels")] + list(values.get("windows", []))
                        + list(values.get("channel_min", [])))
    return (f"<h3>Per window and channel (C({spectral.get('interval_s', 0):g} s))</h3>"
            + _table(head, rows, "sortable", "spectral-table"))


def _plots(facts: RunFacts, base: Path) -> str:
    kinds: Dict[str, List[Path]] = {}
    for plot in facts.plots:
        kinds.setdefault(plot.stem.split("-")[0], []).append(plot)
    out = []
    for kind, plots in sorted(kinds.items()):
        imgs = "".join(f"<img src='{_rel(p, base)}' alt='{_e(p.stem)}'>"
                       for p in plots)
        out.append(f"<details{' open' if kind == 'coherence' else ''}><summary>{_e(kind)} plots "
                   f"({len(plots)})</summary><div class='grid plots'>{imgs}</div></details>")
    return "".join(out)


def _stations_section(facts: RunFacts, base: Path) -> str:
    if not facts.calibrate_reports:
        return ""
    out = ["<section id='stations'><h2>Calibration, per station</h2>"]
    for rep in facts.calibrate_reports:
        body = rep.body
        cols = body.get("columns") or body.get("outputs") or {}
        head = (f"<h3><a href='{_rel(rep.path, base)}'>{_e(rep.path.name)}</a>: "
                f"{_e(', '.join(body.get('methods', [])))} -> {_e(json.dumps(cols))}</h3>")
        facts_line = []
        for key in ("ratio", "r", "eps", "tracker", "chunks"):
            if key in body:
                facts_line.append(f"{key} = {_num(body[key])}")
        table = body.get("reference_table")
        if table:
            facts_line.append(f"reference table {table.get('path') if isinstance(table, dict) else table}")
        groups = body.get("data_groups") or {}
        if groups:   # a run on MSv4 processing sets: each method's result is a data group
            facts_line.append("data groups written: " + ", ".join(
                f"{g.get('data_group')} (partitions {' '.join(g.get('partitions', []))})"
                for g in groups.values()))
        samples = body.get("samples") or {}
        if samples:
            facts_line.append("samples: " + ", ".join(f"{k} {v}" for k, v in samples.items()
                                                       if isinstance(v, int)))
        out.append(head + f"<p class='muted'>{_e('; '.join(facts_line))}</p>")
        out.append(_station_table(body))
        out.append(_phaseref_block(body))
    out.append("</section>")
    return "".join(out)


def _phaseref_block(body: Dict) -> str:
    """The calibrator step's facts and per-antenna terms (hitops/report/phaseref.py)."""
    out = []
    for window in phaseref_windows(body):
        out.append(f"<h3>Phase referencing: {_e(window.column)}</h3><ul>")
        out += [f"<li>{_e(line)}</li>" for line in window.lines]
        out.append("</ul>" + _table(window.head, window.rows, "sortable"))
    return "".join(out)


def _station_table(body: Dict) -> str:
    per: Dict[str, Dict[str, object]] = {}
    for pair in body.get("stations") or []:
        per.setdefault(pair.get("target", "?"), {})["reference station"] = pair.get("reference")
    tracking = body.get("tracking") or {}
    for ant in tracking.get("antennas") or []:
        name = ant.get("antenna", "?")
        for key, value in ant.items():
            if key != "antenna" and isinstance(value, (int, float)):
                per.setdefault(name, {})[key.replace("_", " ")] = value
    for bl in tracking.get("baselines") or []:
        for station in str(bl.get("baseline", "")).split("-"):
            entry = per.setdefault(station, {})
            for key in ("segments", "suspected_slips", "wrap_events"):
                if isinstance(bl.get(key), int):
                    label = f"{key.replace('_', ' ')} (its baselines)"
                    entry[label] = int(entry.get(label, 0)) + bl[key]
    offsets = body.get("offsets") if isinstance(body.get("offsets"), dict) else {}
    solves = (body.get("offset_step") or {}).get("antennas") or offsets.get("antennas") or []
    for solve in solves:
        entry = per.setdefault(solve.get("antenna", "?"), {})
        entry["n0 integers"] = int(entry.get("n0 integers", 0)) + 1
        entry["n0 ambiguous"] = int(entry.get("n0 ambiguous", 0)) + bool(solve.get("ambiguous"))
        if solve.get("k") is not None:
            entry.setdefault("_k", set()).add(int(solve["k"]))
    keys: List[str] = []
    for entry in per.values():
        for key in entry:
            if not key.startswith("_") and key not in keys:
                keys.append(key)
    rows = []
    for station, entry in per.items():
        ks = sorted(entry.get("_k", ()))
        row = [station] + [entry.get(k) for k in keys]
        if ks:
            row.append(", ".join(str(k) for k in ks[:8]) + (" ..." if len(ks) > 8 else ""))
        rows.append(row)
    head = ["station"] + keys + (["n0 k values"] if any(e.get("_k") for e in per.values()) else [])
    return _table(head, rows, "sortable") if rows else "<p class='muted'>no per-station entries</p>"


def _steps_section(steps: StepLog, facts: RunFacts, base: Path) -> str:
    if not steps.steps:
        where = steps.log_dir or "no Stimela log found"
        body = f"<p class='muted'>Steps: unknown ({_e(where)}).</p>"
    else:
        rows = [(s.name, s.status, s.why, "-" if s.seconds is None else
                 _Raw(f"<span data-v='{s.seconds}'>{s.seconds:.0f}</span>"))
                for s in steps.steps]
        body = _table(["step", "status", "why", "time (s, from 1-s log stamps)"], rows,
                      "sortable left", "steps")
        body += f"<p class='muted'>From Stimela's log in {_e(steps.log_dir)} (run started {_e(steps.started)}).</p>"
    receipts = [(name, r.get("applymode", ""), r.get("flagged_fraction"))
                for name, r in facts.receipts.items()]
    if receipts:
        body += "<h3>CASA applycal</h3>" + _table(["receipt", "applymode", "flagged fraction"],
                                                  receipts)
    return f"<section id='steps'><h2>Steps</h2>{body}</section>"


def _warnings_section(steps: StepLog, facts: RunFacts) -> str:
    items = list(steps.warnings) + [f"diagnose: {w}" for w in (facts.diagnose or {}).get("warnings", [])]
    for rep in facts.calibrate_reports:
        for key in ("warnings", "warning"):
            value = rep.body.get(key)
            for w in (value if isinstance(value, list) else [value] if value else []):
                items.append(f"{rep.path.name}: {w}")
    text = "".join(f"<li>{_e(w)}</li>" for w in items) or "<li>none</li>"
    return f"<section id='warnings'><h2>Warnings ({len(items)})</h2><ul>{text}</ul></section>"


def _flags_section(facts: RunFacts, fractions: Dict[Path, Dict[str, float]]) -> str:
    if not facts.flag_versions:
        return ""
    out = ["<section id='flags'><h2>Flag versions</h2><p class='muted'>CASA flag versions kept "
           "beside each set (<code>flagmanager(vis, mode='list')</code> lists them, "
           "<code>mode='restore'</code> restores one). Every step that flags starts from "
           "<code>hitops_original</code> (the flags as simulated or imported) and keeps its result "
           "as its own version; each image uses its own branch's version and diagnose the union of "
           "the branches it compares, so a rerun gives a fresh run's numbers (docs/recipes.md).</p>"]
    for ms, versions in facts.flag_versions.items():
        rows = [(v.name, _Raw(_e(v.comment)), fractions.get(ms, {}).get(v.name)) for v in versions]
        out.append(f"<h3>{_e(ms.name)}</h3>"
                   + _table(["version", "comment", "flagged fraction"], rows, "left"))
    out.append("</section>")
    return "".join(out)


def _provenance_section(prov: Provenance) -> str:
    versions = _table(["package", "version"], sorted(prov.versions.items()))
    params = _table(["parameter", "value", "default"],
                    [(p.name, _Raw(_e(json.dumps(p.value)) if not p.is_default else _e(json.dumps(p.value))
                                   + " <span class='muted'>(default)</span>"),
                      _Raw(_e(json.dumps(p.default)))) for p in prov.parameters], "sortable",
                    "parameters")
    sums = _table(["set", "rows", "SHA-256", "of"],
                  [(c.path, c.rows, _Raw(f"<code>{c.sha256}</code>"), c.what) for c in prov.checksums])
    command = f"<h3>Command</h3><pre>{_e(prov.command)}</pre>" if prov.command else ""
    rerun = (f"<h3>To rerun the same thing</h3><pre id='rerun'>{_e(prov.rerun)}</pre>"
             if prov.rerun else "")
    return (f"<section id='provenance'><h2>Provenance</h2><p>HITOPS commit <code>{_e(prov.commit)}"
            f"</code></p>{command}{rerun}<h3>Versions</h3>{versions}<h3>Parameters</h3>{params}"
            f"<h3>Input sets</h3>{sums}</section>")


def write_page(path: Path, title: str, facts: RunFacts, pictures: List[Picture], steps: StepLog,
               prov: Provenance, fractions: Dict[Path, Dict[str, float]],
               subtitle: Optional[str] = None) -> Path:
    base = path.parent
    sections = [_peak_section(facts), _images_section(pictures, base),
                _coherence_section(facts, base), _stations_section(facts, base),
                _steps_section(steps, facts, base), _warnings_section(steps, facts),
                _flags_section(facts, fractions), _provenance_section(prov)]
    nav = "".join(f"<a href='#{k}'>{v}</a>" for k, v in (
        ("answer", "Answer"), ("images", "Images"), ("coherence", "Coherence"),
        ("stations", "Stations"), ("steps", "Steps"), ("warnings", "Warnings"),
        ("flags", "Flags"), ("provenance", "Provenance")) if f"id='{k}'" in "".join(sections))
    text = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<link rel='icon' href='data:,'><style>{_CSS}</style></head><body>"
            f"<header><h1>{_e(title)}</h1><p>{_e(subtitle or '')}</p></header><nav>{nav}</nav>"
            f"<main>{''.join(sections)}</main><script>{_SORT_JS}</script></body></html>\n")
    tmp = path.with_name(path.name + ".writing")
    tmp.write_text(text)
    tmp.replace(path)
    return path
