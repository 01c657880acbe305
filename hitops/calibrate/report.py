"""Stage 6 of ``hitops calibrate``: the summary in the log, the JSON report, and what follows.

:func:`group_report` turns one group pair's :class:`hitops.calibrate.passes.GroupResult`
into its report entry (and log lines); :func:`finish_after_commit` adds the verdict,
the calibration table and the conversions of the run and writes the JSON once
(:class:`~hitops.calibrate.run_report.RunReport`).
"""

from __future__ import annotations

import functools
import logging
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from ..errors import HitopsError
from .output import FLAG_BACKUP, OutputTransaction
from .passes import GroupResult
from .plan import GroupPlan, RunPlan
from .files import PreparedInputs, record_conversions_and_export
from .run_report import AfterCommit, RunReport, report_path, write_run_report
from .transfer import SampleCounts

log = logging.getLogger("hitops.calibrate")


def _log_samples(samples: SampleCounts) -> int:
    flagged = samples.flagged
    log.info("%d of %d target samples (row x correlation) not calibrated, each counted once: "
             "%d flagged/NaN/zero in the target, %d without a reference row, %d with the "
             "reference sample flagged/NaN/zero%s; %d calibrated", flagged, samples.n_samples,
             samples.target_invalid, samples.no_reference_row, samples.reference_invalid,
             (f", {samples.other_uncalibrated} other" if samples.other_uncalibrated else ""),
             samples.n_samples - flagged)
    return flagged


def _tracking_entry(run: RunPlan, group: GroupPlan, result: GroupResult) -> dict:
    match, setup, solution = group.match, group.tracking, result.offsets
    entry = result.tracker.report(match.times)
    if not result.tracker.segmented:   # count: wrap events per baseline, nothing to resolve
        return entry
    option = "--offset-model" if run.columns.offset_is_model else "--offset-reference-column"
    if solution.solves is not None:
        what = "the model" if run.columns.offset_is_model else "the reference column"
        entry["segment_offsets"] = (f"offset step per antenna and segment, solved on the "
                                    f"lattice against {what} ({option})")
    elif solution.segment_k is not None:
        entry["segment_offsets"] = f"offset step per segment ({option})"
    else:
        entry["segment_offsets"] = ("per antenna (antenna mode)" if setup.tracker == "antenna"
                                    else "best guess")
    log_tracking(entry, setup, solution.segment_k is not None)
    return entry


def group_report(run: RunPlan, group: GroupPlan, result: GroupResult, tx: OutputTransaction,
                 started: float) -> Dict:
    """The log lines and the report of one finished group pair."""
    match, samples, solution = group.match, result.samples, result.offsets
    flagged = _log_samples(samples)
    for b, name in enumerate(match.baseline_names):
        log.info("wraps %s: %s", name, ", ".join(f"{cn} {int(result.wrap_events[b, c])}"
                                                 for c, cn in enumerate(match.corr_names)))
    tracking = _tracking_entry(run, group, result)
    columns = run.columns
    report = {
        "ref_ms": run.ref_ms, "target_ms": run.target_ms, "methods": run.methods,
        "columns": run.outputs, "ratio": group.ratio, "r": group.r, "eps": group.eps,
        "ratio_source": group.ratio_source, "time_tolerance_s": match.tolerance,
        "tracker": run.opts.tracking.tracker, "chunks": group.n_chunks, "stations": match.pairing,
        "tracking": tracking,
        "flags": {"column": "FLAG", "backup_column": FLAG_BACKUP, "flag_updated": tx.flag_written,
                  "input_flags": columns.flag, "backup_created": tx.backup_written},
        "rows": {"target": int(group.n_target_rows), "matched": group.n_matched,
                 "reference_unused": group.n_ref_unused},
        "samples": {"target": samples.n_samples, "flagged": flagged,
                    "no_reference_row": samples.no_reference_row,
                    "target_invalid": samples.target_invalid,
                    "reference_invalid": samples.reference_invalid,
                    "other_uncalibrated": samples.other_uncalibrated,
                    "jump_flagged": result.jump_flagged,
                    "causes": "disjoint: target_invalid + no_reference_row + reference_invalid "
                              "+ other_uncalibrated = flagged"},
        "wraps": [{"baseline": name, "correlation": cn,
                   "wrap_events": int(result.wrap_events[b, c])}
                  for b, name in enumerate(match.baseline_names)
                  for c, cn in enumerate(match.corr_names)],
        "offset_step": {
            "column": run.opts.n0.offset_reference_column,
            "max_offset_wraps": int(run.opts.n0.max_offset_wraps),
            "applied_to": ([m for m in run.methods if m in ("pwc", "cwu")]
                           if solution.ran else []),
            "per": "segment" if solution.segment_k is not None else "scan",
            "model": run.opts.n0.offset_model or None,
            "solve": ("antenna lattice" if solution.solves is not None
                      else "baseline" if solution.ran else None),
            "antennas": solution.antennas,
            "solves": solution.solves if solution.solves is not None else [],
            "warning": no_offset_step_warning(run, group, solution),
            "series": solution.series},
        "time_s": time.perf_counter() - started,
        "timings_s": {k: round(v, 4) for k, v in run.timings.items()},
    }
    if group.channels is not None:   # per-channel ratios: the frequencies and R_k range
        report["channels"] = group.channels.as_report()
    return report


def combined_report(run: RunPlan, reports: List[Dict]) -> Dict:
    """One report for several group pairs: the run's entries, then one entry per group."""
    first = reports[0]
    groups = []
    for group, rep in zip(run.groups, reports):
        pair = group.pair
        entry = {"field": pair.tgt.field, "ref_field_id": pair.ref.key[0],
                 "target_field_id": pair.tgt.key[0], "ref_spw": pair.ref.spw,
                 "target_spw": pair.tgt.spw, "ref_freq_hz": pair.ref.freq,
                 "target_freq_hz": pair.tgt.freq}
        entry.update({k: v for k, v in rep.items()
                      if k not in ("ref_ms", "target_ms", "methods", "columns", "flags",
                                   "time_s", "timings_s")})
        groups.append(entry)
    return {"ref_ms": first["ref_ms"], "target_ms": first["target_ms"],
            "methods": first["methods"], "columns": first["columns"],
            "ratio": [e["ratio"] for e in groups], "flags": first["flags"],
            "groups": groups, "time_s": first["time_s"],
            "timings_s": {k: round(sum(r["timings_s"].get(k, 0.0) for r in reports), 4)
                          for k in first["timings_s"]}}


def finish_after_commit(run: RunPlan, report: Dict, result: Optional[GroupResult],
                 started: float, prepared: PreparedInputs,
                 group_results: Sequence[GroupResult] = ()) -> Dict:
    """The verdict, the calibration table and conversions of a run; the JSON report written
    once (hitops/calibrate/run_report.py).  Returns the report with ``report_path``.

    ``report``: the sections of the run (group_report or combined_report); ``result``:
    the one group's GroupResult, or None for a run of several groups; ``group_results``:
    every group's (a per-channel --caltable holds all windows).
    """
    opts = run.opts
    path = report_path(opts, run.target_ms)
    out = RunReport(path, report, AfterCommit(verdict=_verdict_entry(run, result, path)))
    if "verdict" in run.timings and "timings_s" in report:   # made after the summary
        report["timings_s"]["verdict"] = round(run.timings["verdict"], 4)
    caltable = None
    if opts.output.caltable and run.groups[0].channels is not None:
        caltable = functools.partial(_write_fringe_table, run, group_results)
    elif opts.output.caltable:
        caltable = functools.partial(_write_caltable, run, run.groups[0], result)
    body = write_run_report(out, caltable, lambda after: record_conversions_and_export(
        after, opts, run.ref_ms, run.target_ms, run.outputs, run.methods, prepared))
    elapsed = time.perf_counter() - started
    log.info("wrote %s to %s; report %s; %.2f s (%s)", ", ".join(run.outputs.values()),
             run.target_ms, path, elapsed,
             ", ".join(f"{k} {v:.2f}" for k, v in run.timings.items()))
    warnings = [report["offset_step"]["warning"]] if "offset_step" in report else \
        [e["offset_step"]["warning"] for e in report.get("groups", [])]
    for warning in dict.fromkeys(w for w in warnings if w):
        log.warning(warning)
    return body


def _verdict_entry(run: RunPlan, result: Optional[GroupResult], path: Path) -> Optional[Dict]:
    """The report's verdict: made on a one-group, one-chunk run; why not otherwise; None
    with --no-verdict."""
    if run.opts.run.no_verdict:
        return None
    if result is None:
        # the verdict reads each band as one group (hitops/calibrate/verdict_sample.py)
        log.info("no verdict: the sets hold several field/spectral-window groups and the "
                 "verdict reads each band as one")
        return {"skipped": "several groups"}
    if result.n_chunks == 1:
        return _verdict(run, run.groups[0], str(path))
    # a run whose memory is bounded by --chunk-rows makes no verdict
    log.info("no verdict: the sets are larger than --chunk-rows (%d chunks) and the verdict "
             "is made in one-chunk runs only; raise --chunk-rows to get one", result.n_chunks)
    return {"skipped": f"{result.n_chunks} chunks"}


def no_offset_step_warning(run: RunPlan, group: GroupPlan, solution) -> Optional[str]:
    """The warning of a run that wrote PWC/CWU without the n0 step (None otherwise)."""
    written = [run.outputs[m] for m in ("pwc", "cwu") if m in run.outputs]
    # integer R leaves no n0 offset on one channel; across a window it leaves a slope
    across = group.channels is not None and group.channels.across_channels
    if not written or solution.ran or (group.eps == 0.0 and not across):
        return None
    per = ("antenna (closure phases are right, the phases themselves are not)"
           if run.opts.tracking.tracker == "antenna" else "baseline")
    return (f"{' and '.join(written)} carr{'y' if len(written) > 1 else 'ies'} a constant "
            f"2 pi eps n0 per {per} and scan (or tracking segment): no n0 offset step ran. Before "
            "imaging, run the offset step (--offset-model point, or a model column; "
            "--offset-reference-column) or self-calibrate; imaged as it is, CLEAN can diverge "
            "(docs/calibrate.md, 'The n0 offset step')")


def _write_fringe_table(run: RunPlan, results: Sequence[GroupResult]) -> Dict:
    """--caltable of a per-channel transfer: one CASA 'Fringe Jones' table for every target
    window, phase at the window centre and a delay across it (hitops/calibrate/gains.py)."""
    from ..io.caltable import scan_of_times
    from ..solutions.write import write_fringe_table
    from .gains import antenna_turns, fringe_window

    windows = []
    for group, result in zip(run.groups, results):
        match = group.match
        psi, valid = antenna_turns(result.tracker.antenna_phase, result.tracker.antenna_segment,
                                   group.grid.scans.scan_of_time, offsets=result.offsets.antennas)
        windows.append(fringe_window(
            psi, valid, match.times, scan_of_times(run.target_ms, match.times), group.ratio,
            group.channels.ref_freq, group.pair.tgt.spw, group.pair.tgt.key[0],
            group.channels.tgt_centre))
    n_ant = len(run.groups[0].antenna_names)
    n_row = write_fringe_table(run.opts.output.caltable, run.target_ms, windows, n_ant,
                               overwrite=bool(run.opts.output.overwrite))
    n_valid = int(sum(w.valid.sum() for w in windows))
    log.info("wrote the antenna solutions to %s (CASA Fringe Jones: phase at each window's "
             "centre and a delay, %d rows for %d window(s); %d solutions)", run.opts.output.caltable,
             n_row, len(windows), n_valid)
    return {"path": str(run.opts.output.caltable), "type": "Fringe Jones", "rows": n_row,
            "solutions": n_valid}


def _write_caltable(run: RunPlan, group: GroupPlan, result: GroupResult) -> Dict:
    """--caltable: the antenna tracker's gains as a CASA G Jones table (hitops/calibrate/gains.py)."""
    from ..io.caltable import write_gain_table
    from .gains import antenna_gain_phases

    match, tracker = group.match, result.tracker
    phase, valid = antenna_gain_phases(tracker.antenna_phase, tracker.antenna_segment,
                                       group.grid.scans.scan_of_time, group.ratio, group.eps,
                                       offsets=result.offsets.antennas)
    # the cross hands of the column are transferred per baseline: the table holds the
    # parallel hands' antenna gains, from which CASA forms every correlation
    path = write_gain_table(run.opts.output.caltable, run.target_ms, match.times, phase, valid,
                            match.corr_names, overwrite=bool(run.opts.output.overwrite))
    n_valid = int(valid.sum())
    log.info("wrote the antenna gains to %s (CASA G Jones, %d times x %d antennas; %d "
             "solutions, %d flagged)", path, phase.shape[0], phase.shape[1], n_valid,
             int(valid.size - n_valid))
    return {"path": str(path), "solutions": n_valid, "flagged": int(valid.size - n_valid)}


def _verdict(run: RunPlan, group: GroupPlan, report_path: str) -> Dict:
    """Will FPT help here?  The prediction per baseline (hitops/calibrate/verdict.py)."""
    from .verdict import log_verdict, predict, summary

    opts = run.opts
    started = time.perf_counter()
    try:
        verdict = predict(run.ref_ms, run.target_ms, group.ratio, opts.input.ref_column,
                          opts.input.target_column, float(opts.run.verdict_interval),
                          ref_meta=run.ref_meta, tgt_meta=run.tgt_meta,
                          target_flags_of=next(iter(run.outputs.values())))
    except HitopsError as err:   # the columns are written: say why there is no verdict
        log.warning("no verdict: %s", err)
        return {"error": str(err)}
    log_verdict(verdict, methods_transfer_baselines=opts.tracking.tracker != "antenna",
                has_model=bool(opts.input.ref_model_column), report_path=report_path)
    run.timings["verdict"] = time.perf_counter() - started
    return {**verdict.as_dict(), "summary": summary(verdict)}


def log_tracking(rep: Dict, setup, resolved: bool = False) -> None:
    """Confidence numbers per baseline (and antenna), and what is unresolved."""
    for e in rep["baselines"]:
        log.info("tracking %s: %d suspected slips (%d samples), %d bridged gaps, %d segments "
                 "(%d after long gaps), %d jumps%s", e["baseline"], e["suspected_slips"],
                 e["suspect_samples"], e["bridged_gaps"], e["segments"], e["long_gap_segments"],
                 e["jumps"], _jumps(e))
    for e in rep.get("antennas", []):
        log.info("tracking antenna %s: %d suspected slips, %d bridged gaps, %d segments (%d after "
                 "long gaps), %d jumps%s", e["antenna"], e["suspected_slips"], e["bridged_gaps"],
                 e["segments"], e["long_gap_segments"], e["jumps"], _jumps(e))
    if setup.tracker == "smooth":
        _log_smooth_segments(rep, setup, resolved)
    elif setup.tracker == "antenna":
        n_seg = sum(e["long_gap_segments"] + e["jumps"] for e in rep.get("antennas", []))
        if n_seg:
            log.warning("%d antenna segment(s) start after long gaps or jumps: their wrap offset "
                        "is per antenna (closure phases are unaffected; an antenna-based phase "
                        "calibration per segment absorbs it)", n_seg)


def _jumps(e: Dict) -> str:
    return "".join(f"; jump {j['correlation']} at +{j['time_from_start_s']:.0f} s "
                   f"({j['size_deg']:.0f} deg)" for j in e["jump_list"][:5])


def _log_smooth_segments(rep: Dict, setup, resolved: bool) -> None:
    if resolved:
        n_seg = sum(e["long_gap_segments"] + e["jumps"] for e in rep["baselines"])
        if n_seg:
            log.info("%d segment(s) after long gaps or jumps: their wrap offsets were resolved "
                     "by the offset step per segment (see offset_step in the report)", n_seg)
        return
    unresolved = [e for e in rep["baselines"]
                  if e["long_gap_segments"] or (e["jumps"] and setup.jump_action == "segment")]
    if unresolved:
        log.warning("%d baseline(s) have segments after long gaps or jumps whose wrap offset "
                    "is a best guess (not resolved): %s; use --tracker antenna (n0 per "
                    "antenna, closes) or --jump-action flag, or check them against a "
                    "reference", len(unresolved),
                    ", ".join(f"{e['baseline']} ({e['long_gap_segments']} gaps, "
                              f"{e['jumps']} jumps)" for e in unresolved[:10]))
