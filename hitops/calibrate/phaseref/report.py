"""The calibrator step's report: per window and antenna the phase and delay solved on
each calibrator scan, their means and how much they move between scans (the error the
interpolation onto the target's scans cannot see), and one summary log line."""

from __future__ import annotations

import logging
from typing import Dict, List

import numpy as np

log = logging.getLogger("hitops.calibrate")


def _step_rms(values: np.ndarray) -> float:
    """rms of the change between consecutive scans (0 with one scan)."""
    return float(np.sqrt(np.mean(np.diff(values) ** 2))) if values.size > 1 else 0.0


def window_report(solution, names: List[str], n_target_rows: int, n_flagged: int) -> Dict:
    """One spectral window's entry: scans, and per antenna and hand the solutions."""
    antennas: Dict[str, Dict] = {}
    for a, name in enumerate(names):
        per_hand = {}
        for h, hand in enumerate(solution.hands):
            ok = np.array([s.valid[a, h] for s in solution.scans])
            if not ok.any():
                continue
            phase = np.unwrap(np.array([s.phase[a, h] for s in solution.scans])[ok])
            delay = np.array([s.delay[a, h] for s in solution.scans])[ok]
            per_hand[hand] = {
                "phase_deg": [round(float(np.degrees(p)), 4) for p in np.angle(np.exp(1j * phase))],
                "delay_ns": [round(float(d * 1e9), 6) for d in delay],
                "phase_mean_deg": round(float(np.degrees(np.angle(np.mean(np.exp(1j * phase))))), 4),
                "delay_mean_ns": round(float(np.mean(delay) * 1e9), 6),
                "phase_rms_between_scans_deg": round(float(np.degrees(_step_rms(phase))), 4),
                "delay_rms_between_scans_ns": round(_step_rms(delay) * 1e9, 6),
            }
        antennas[name] = per_hand or {"unsolved": True}
    n_ant = len(names)
    baselines = {}
    for b, code in enumerate(solution.baselines):
        label = f"{names[code // n_ant]}-{names[code % n_ant]}"
        baselines[label] = {hand: round(float(np.degrees(np.angle(
            solution.residual[b, :, h].sum()))), 3) for h, hand in enumerate(solution.hands)}
    return {"spw": solution.spw, "freq_hz": solution.freq, "refant": names[solution.refant],
            "scans": [{"scan": s.scan, "time": s.time} for s in solution.scans],
            "target_rows": n_target_rows, "target_rows_flagged": n_flagged,
            "antennas": antennas, "baseline_residual_deg": baselines}


def _integers_text(windows: List[Dict]) -> str:
    """How each window's per-scan integers were found, for the log line."""
    parts = []
    for w in windows:
        found = w.get("integers", {})
        if found.get("rule") == "carried":
            parts.append(f"window {w['spw']}: counts carried across the switches")
            continue
        cal, tgt = found.get("calibrator", {}), found.get("target", {})
        parts.append(f"window {w['spw']}: each scan's integer from its delay and phase "
                     f"({cal.get('nonzero', 0)} calibrator and {tgt.get('nonzero', 0)} target "
                     f"scan series moved, {tgt.get('undecided_scans', 0)} target series "
                     "flagged unclear)")
    return "; ".join(parts)


def log_summary(entry: Dict) -> None:
    """One line per column: scans, rows, the largest scan-to-scan movement and where, the
    integers' rule and counts, the model used."""
    for column, windows in entry["methods"].items():
        worst_phase, worst_delay = (0.0, "-"), (0.0, "-")
        n_scans = rows = flagged = 0
        for w in windows:
            n_scans = max(n_scans, len(w["scans"]))
            rows += w["target_rows"]
            flagged += w["target_rows_flagged"]
            for name, hands in w["antennas"].items():
                for hand, v in hands.items():
                    if hand == "unsolved":
                        continue
                    if v["phase_rms_between_scans_deg"] >= worst_phase[0]:
                        worst_phase = (v["phase_rms_between_scans_deg"], f"{name} {hand}")
                    if v["delay_rms_between_scans_ns"] >= worst_delay[0]:
                        worst_delay = (v["delay_rms_between_scans_ns"], f"{name} {hand}")
        log.info("phase referencing on %s (model: %s): %d calibrator scan(s), %d target rows "
                 "of %s corrected (%d flagged: antenna unsolved); %s; largest rms between "
                 "scans %.2f deg (%s), %.4f ns (%s); per antenna in the report",
                 entry["calibrator_field"], entry.get("calibrator_model", "point"), n_scans,
                 rows, column, flagged, _integers_text(windows), worst_phase[0],
                 worst_phase[1], worst_delay[0], worst_delay[1])
