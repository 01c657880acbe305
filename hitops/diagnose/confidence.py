"""Wrap-tracking confidence numbers from ``hitops calibrate``'s JSON report.

``hitops calibrate`` writes ``TARGET_MS.hitops-calibrate.json`` with, per
baseline (and per antenna with ``--tracker antenna``), the number of
suspected slips, bridged gaps, segments and instrumental jumps of the
reference-band wrap tracking (docs/tracking.md).  Diagnose shows them beside
the coherence of each baseline: a baseline whose PWC output has a low
coherence factor *and* suspected slips or unresolved segments points at the
tracking, not at the troposphere.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from ..errors import InputError

#: numbers shown in the tables (report key -> short column name)
FIELDS = {"suspected_slips": "slips?", "bridged_gaps": "bridged", "segments": "segments",
          "long_gap_segments": "gap_segs", "jumps": "jumps"}


def default_report_path(ms: str) -> Path:
    return Path(str(ms).rstrip("/") + ".hitops-calibrate.json")


def load(ms: str, report: Optional[str]) -> Tuple[Optional[dict], List[str]]:
    """(tracking info, warnings) from ``report`` or, when None, the default file beside ``ms``.

    Tracking info: ``{"tracker", "baselines": {name: {field: n}},
    "antennas": {name: {field: n}}, "path"}`` (an antenna of a ``--reference-table`` run:
    ``wraps``, the wraps counted in its solutions); None when there is no report.
    An explicitly given report that is missing or unreadable is an error.
    """
    explicit = report is not None and str(report) != ""
    path = Path(report) if explicit else default_report_path(ms)
    if not path.exists():
        if explicit:
            raise InputError(f"--calibrate-report {path}: no such file; give the JSON report "
                             "hitops calibrate wrote (TARGET_MS.hitops-calibrate.json)")
        return None, []
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        if explicit:
            raise InputError(f"--calibrate-report {path}: not a readable JSON report ({err})") \
                from None
        return None, [f"calibrate report {path} is not readable JSON ({err}); tracking "
                      "columns left out"]
    tracking = data.get("tracking") if isinstance(data, dict) else None
    if not isinstance(tracking, dict) or "baselines" not in tracking:
        msg = (f"calibrate report {path} holds no wrap-tracking section (written by an older "
               "hitops calibrate?); tracking columns left out")
        if explicit:
            raise InputError(f"--calibrate-report: {msg}")
        return None, [msg]
    warnings = []
    target = data.get("target_ms")
    if target and os.path.realpath(target) != os.path.realpath(str(ms)):
        warnings.append(f"calibrate report {path} was written for {target}, not {ms}")
    tracker = tracking.get("setup", {}).get("tracker", data.get("tracker", "count"))
    baselines = {}
    for e in tracking["baselines"]:
        baselines[e["baseline"]] = {k: int(e[k]) for k in FIELDS if k in e}
        baselines[e["baseline"]]["wrap_events"] = int(e.get("wrap_events", 0))
    # a --reference-table run tracks per antenna: the wraps counted in its solutions
    antennas = {e["antenna"]: {k: int(e[k]) for k in (*FIELDS, "wraps") if k in e}
                for e in tracking.get("antennas", [])}
    return {"tracker": tracker, "baselines": baselines, "antennas": antennas,
            "verdict": _verdicts(data.get("verdict")), "path": str(path)}, warnings


def _verdicts(section) -> Dict[str, dict]:
    """{baseline: {"predicted_pct", "verdict"}}: calibrate's prediction, mean over hands."""
    out: Dict[str, dict] = {}
    if not isinstance(section, dict):
        return out
    changes: Dict[str, list] = {}
    for e in section.get("baselines", []):
        if e.get("predicted_change") is not None:
            changes.setdefault(e["baseline"], []).append(float(e["predicted_change"]))
    for name, values in changes.items():
        pct = 100.0 * sum(values) / len(values)
        out[name] = {"predicted_pct": pct,
                     "verdict": "help" if pct > 1 else "hurt" if pct < -1 else "neutral"}
    return out


def antenna_totals(info: dict, antenna: str, baselines: List[str]) -> Dict[str, int]:
    """Per-antenna numbers: the antenna mode's own, else the sums over its baselines."""
    if antenna in info["antennas"]:
        return dict(info["antennas"][antenna])
    if not any(k in e for e in info["baselines"].values() for k in FIELDS):
        return {}     # --tracker count reports wrap events only
    out = {k: 0 for k in FIELDS}
    for name in baselines:
        for k in FIELDS:
            out[k] += info["baselines"].get(name, {}).get(k, 0)
    return out


def annotate(comparisons: List[dict], info: Optional[dict]) -> None:
    """Add ``tracking`` entries to every ranked baseline and antenna summary."""
    if info is None:
        return
    for comp in comparisons:
        for r in comp["ranking"]:
            r["tracking"] = info["baselines"].get(r["baseline"])
            r["predicted"] = info.get("verdict", {}).get(r["baseline"])
        for a in comp["antennas"]:
            mine = [r["baseline"] for r in comp["ranking"]
                    if a["antenna"] in (r["ant1"], r["ant2"])]
            a["tracking"] = antenna_totals(info, a["antenna"], mine)


def cell(entry: Optional[dict]) -> str:
    """Compact text cell: slips?/bridged/segments/jumps."""
    if entry and "wraps" in entry and not any(k in entry for k in FIELDS):
        return f"{entry['wraps']} wraps"      # a --reference-table run's antenna
    if not entry or not any(k in entry for k in FIELDS):
        return "-"
    return "/".join(str(entry.get(k, 0)) for k in ("suspected_slips", "bridged_gaps",
                                                     "segments", "jumps"))
