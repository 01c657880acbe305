"""What a run's calibrator step did, read from calibrate's report for the page.

``hitops calibrate --calibrator-field`` (hitops/calibrate/phaseref/) reports, per output
column and target window, the calibrator, the model its rows were divided by, how each
scan's integer was found (the ``integers`` entry: the rule, how many scan series were
decided, the smallest margin, target scans left unclear and the rows flagged for them)
and each antenna's solved phase and delay per hand.  This module turns that into the
lines and table rows the page shows beside the per-station facts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Sequence


@dataclass(frozen=True)
class PhaseRefWindow:
    """One output column and target window of the calibrator step, ready to show."""

    column: str
    lines: List[str]                  # what the step did, one fact per line
    head: Sequence[str]               # the per-antenna table's columns
    rows: List[Sequence]              # per antenna and hand


_HEAD = ("station", "hand", "phase mean (deg)", "delay mean (ns)",
         "phase rms between scans (deg)", "delay rms between scans (ns)")


def _integer_lines(integers: Dict) -> List[str]:
    lines = [f"each scan's integer by the {integers.get('rule', '?')} rule"]
    for side in ("calibrator", "target"):
        part = integers.get(side) or {}
        if part:
            text = (f"{side}: {part.get('decided', '?')} scan series decided, "
                    f"{part.get('nonzero', '?')} moved, smallest margin "
                    f"{part.get('min_margin', '?')}")
            if part.get("undecided_scans"):
                text += (f"; {part['undecided_scans']} scan series unclear, "
                         f"{part.get('rows_flagged', 0)} rows flagged")
            lines.append(text)
    return lines


def phaseref_windows(body: Dict) -> List[PhaseRefWindow]:
    """Every (column, window) of a calibrate report's ``phase_referencing`` entry."""
    entry = body.get("phase_referencing") or {}
    out = []
    for column, windows in (entry.get("methods") or {}).items():
        for window in windows:
            lines = [f"calibrator {entry.get('calibrator_field')} (field "
                     f"{entry.get('field_id')}) on fields {entry.get('target_field_ids')}",
                     f"model: {window.get('calibrator_model') or entry.get('calibrator_model')}",
                     f"window {window.get('spw')} at {window.get('freq_hz', 0) / 1e9:.3f} GHz, "
                     f"reference antenna {window.get('refant')}, "
                     f"{len(window.get('scans') or [])} calibrator scans",
                     f"target rows {window.get('target_rows')}, of which "
                     f"{window.get('target_rows_flagged')} flagged for an antenna without a "
                     "calibrator solution"]
            lines += _integer_lines(window.get("integers") or {})
            rows = []
            for station, hands in (window.get("antennas") or {}).items():
                for hand, terms in hands.items():
                    rows.append((station, hand, terms.get("phase_mean_deg"),
                                 terms.get("delay_mean_ns"),
                                 terms.get("phase_rms_between_scans_deg"),
                                 terms.get("delay_rms_between_scans_ns")))
            out.append(PhaseRefWindow(column, lines, _HEAD, rows))
    return out
