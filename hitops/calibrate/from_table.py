"""``hitops calibrate --reference-table``: the reference band's antenna phases from a CASA table.

Instead of tracking REF_MS's visibility phases, the antenna phases come from a
calibration table solved on REF_MS (fringefit 'Fringe Jones', gaincal 'G Jones' or
'T Jones').  :mod:`hitops.solutions` counts each antenna's wraps (the rates bridging the
solutions), re-refers reference antenna changes and transfers them per antenna and per
target channel (R_k = nu_k / nu_ref): one :class:`~hitops.solutions.transfer.TargetWindow`
per (field, target window).  This module applies them to the target's column:

    OUT_pq(k) = TARGET_pq(k) * exp(-i (theta_p(k) - theta_q(k))),

theta evaluated from those windows exactly as CASA applycal evaluates the ``--caltable``
table written from them (:mod:`hitops.solutions.apply`), so the column and applycal of
the table agree.  Being per antenna, closure phases are kept by construction.

Methods: ``pwc`` counts the wraps (theta = R_k * u, u the unwrapped solution phase, which
is the paper's PWC per channel); ``cfpt`` scales the wrapped solution phase (R_k * phi, what
a row-by-row transfer such as AIPS SNCOR 'XFER' does), for comparison; ``cwu`` is refused:
rewrapping cancels the target band's unwrap, so with the same reference wrap count it
is ``pwc`` (GUIDE section 1).  With ``--offset-model`` or ``--offset-reference-column``,
``pwc`` first solves each antenna's integer per segment (the n0 step,
:mod:`hitops.calibrate.n0.table`) in a pass over the target set.  The output column,
FLAG and the staging follow the visibility path
(:class:`~hitops.calibrate.output.OutputTransaction`: whole or not at all).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from ..errors import InputError
from ..io import tables
from ..solutions.api import PreparedTransfer, prepare_transfer, transfer_report, write_target_table
from ..solutions.apply import all_fields, apply_window
from .inputs import CalibrateOptions, check_inputs
from .commit import stage_and_commit
from .output import OutputTransaction
from .rules import PreparedInputs, finish_report

log = logging.getLogger("hitops.calibrate")

#: receptors (ANTENNA1's, ANTENNA2's) of each correlation type (casacore Stokes codes)
RECEPTORS = {5: (0, 0), 6: (0, 1), 7: (1, 0), 8: (1, 1),      # RR RL LR LL
             9: (0, 0), 10: (0, 1), 11: (1, 0), 12: (1, 1)}   # XX XY YX YY
#: what each method makes of the table's solution phases
WRAP_COUNTING = {"pwc": True, "cfpt": False}
#: visibilities (rows x channels x correlations) per chunk when --chunk-rows is 0
CHUNK_VISIBILITIES = 4_000_000


def refuse_options(opts: CalibrateOptions, methods: List[str]) -> None:
    """Options of the visibility path that mean nothing with a table: one line each."""
    table = f"--reference-table {opts.reference_table}"
    if "cwu" in methods:
        raise InputError(f"--method cwu with {table}: on the table's wrap counts CWU equals PWC "
                         "(rewrapping cancels the target's unwrap); use --method pwc "
                         "(or pwc,cfpt to compare with the uncounted transfer)")
    step = "--offset-model" if opts.offset_model else "--offset-reference-column"
    if (opts.offset_model or opts.offset_reference_column) and "pwc" not in methods:
        raise InputError(f"{step} with {table} and --method {','.join(methods)}: the n0 step "
                         "solves the integers of the counted transfer; add pwc to --method")
    if opts.calibrator_field:
        raise InputError(f"--calibrator-field {opts.calibrator_field} with {table}: the calibrator "
                         "step works on the visibility path's per-baseline counts; run it without "
                         "--reference-table, or solve the calibrator's scans of the written column "
                         "in CASA (fringefit field=..., then applycal to the target)")
    given = [(bool(opts.ref_model_column), "--ref-model-column"), (opts.ratio is not None, "--ratio"),
             (bool(opts.average_channels), "--average-channels"), (bool(opts.scheduler), "--scheduler"),
             (opts.tracker != "count", f"--tracker {opts.tracker}")]
    for present, flag in given:
        if present:
            raise InputError(f"{flag} with {table}: the table's solutions replace REF_MS's "
                             "visibilities (their wraps counted by hitops.solutions, each target "
                             f"channel at R_k = nu_k / nu_ref); drop {flag}")


@dataclass(frozen=True)
class TargetLayout:
    """What the writer needs of TARGET_MS's subtables."""

    spw_of_ddid: np.ndarray                 # (n_ddid,) SPECTRAL_WINDOW_ID
    receptors_of_ddid: Tuple[np.ndarray, ...]   # per DATA_DESC_ID: (n_corr, 2) receptor of ant1, ant2
    chan_freq: Tuple[np.ndarray, ...]       # per spectral window: (n_chan,) Hz


def read_layout(target_ms: str) -> TargetLayout:
    with tables.subtable(target_ms, "DATA_DESCRIPTION") as t:
        spw = t.getcol("SPECTRAL_WINDOW_ID")
        pol = t.getcol("POLARIZATION_ID")
    with tables.subtable(target_ms, "POLARIZATION") as t:
        corr = [np.asarray(t.getcell("CORR_TYPE", int(p)), int) for p in pol]
    with tables.subtable(target_ms, "SPECTRAL_WINDOW") as t:
        freq = tuple(np.asarray(t.getcell("CHAN_FREQ", i), float) for i in range(t.nrows()))
    receptors = []
    for ddid, types in enumerate(corr):
        unknown = [int(c) for c in types if int(c) not in RECEPTORS]
        if unknown:
            raise InputError(f"TARGET_MS '{target_ms}' data description {ddid} has correlation "
                             f"type(s) {unknown} (casacore Stokes codes): a table's antenna gains "
                             "apply to RR/RL/LR/LL or XX/XY/YX/YY; give circular or linear hands")
        receptors.append(np.array([RECEPTORS[int(c)] for c in types], int))
    return TargetLayout(spw.astype(int), tuple(receptors), freq)


@dataclass
class ChunkOutput:
    """One chunk's corrected visibilities per method and the samples left uncalibrated."""

    columns: Dict[str, np.ndarray]
    uncalibrated: np.ndarray    # (n_row, n_corr) bool


def _window_rows(prepared: PreparedTransfer, layout: "TargetLayout", ddid: np.ndarray,
                 field: np.ndarray):
    """(index, window, receptors, rows) of every transferred window and data description
    in the chunk."""
    for j, window in enumerate(prepared.targets):
        for d in np.flatnonzero(layout.spw_of_ddid == window.spw):
            rows = np.flatnonzero((ddid == d) & (field == window.field))
            if rows.size:
                yield j, window, layout.receptors_of_ddid[d], rows


def correct_chunk(transfers: Dict[str, PreparedTransfer], layout: TargetLayout, cols: Dict) -> ChunkOutput:
    """The target rows of one chunk corrected by each method's transferred antenna terms.

    Every field's solutions of a window are one series, as applycal interpolates them
    with its default gainfield (hitops/solutions/apply.py); a window without any stays 0.
    """
    data = cols["data"]
    n_row, _, n_corr = data.shape
    ddid = cols["DATA_DESC_ID"]
    out = {m: np.zeros(data.shape, np.complex64) for m in transfers}
    calibrated = np.ones((n_row, n_corr), bool)
    for method, prepared in transfers.items():
        done = np.zeros((n_row, n_corr), bool)
        merged = all_fields(prepared.targets)
        for d in np.unique(ddid):
            window = merged.get(int(layout.spw_of_ddid[d]))
            if window is None:
                continue
            rows = np.flatnonzero(ddid == d)
            corrected = apply_window(window, cols["TIME"][rows], cols["ANTENNA1"][rows],
                                     cols["ANTENNA2"][rows], layout.receptors_of_ddid[d],
                                     data[rows], layout.chan_freq[window.spw])
            out[method][rows] = corrected.data
            done[rows] = corrected.calibrated
        calibrated &= done
    return ChunkOutput(out, ~calibrated)


def _chunk_columns(t, columns, start: int, n: int, offset_column=None) -> Dict:
    cols = {name: t.getcol(name, start, n) for name in
            ("TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "FIELD_ID", "FLAG_ROW")}
    cols["data"] = t.getcol(columns.target_data, start, n)
    cols["flag"] = t.getcol(columns.flag, start, n)
    if offset_column:
        cols["offset"] = t.getcol(offset_column, start, n)
    return cols


def _chunks(target_ms: str, columns, chunk_rows: int, offset_column=None):
    """(start, n, columns) of every chunk of the target set, read with python-casacore."""
    with tables.main_table(target_ms) as t:
        n_total = t.nrows()
    for start in range(0, n_total, chunk_rows):
        n = min(chunk_rows, n_total - start)
        with tables.main_table(target_ms) as t:
            yield start, n, _chunk_columns(t, columns, start, n, offset_column)


def offset_step(prepared: PreparedTransfer, layout: TargetLayout, columns, chunk_rows: int,
                opts: CalibrateOptions, target_ms: str):
    """The n0 step (hitops/calibrate/n0/table.py): a first pass over the target set,
    one lattice solve per field and receptor; the transfer with the integers taken out."""
    from .n0.table import accumulate, apply_offsets, solve, solve_windows

    offset_column = None if columns.offset_is_model and not columns.model else columns.offset
    solve_on = set(solve_windows(prepared).values())
    sums: Dict = {}
    for _, _, cols in _chunks(target_ms, columns, chunk_rows, offset_column):
        result = correct_chunk({"pwc": prepared}, layout, cols)
        bad = cols["flag"] | cols["FLAG_ROW"][:, None, None] | result.uncalibrated[:, None, :]
        for j, _, receptors, rows in _window_rows(prepared, layout, cols["DATA_DESC_ID"],
                                                  cols["FIELD_ID"]):
            if j in solve_on:
                model = np.angle(cols["offset"][rows]) if offset_column else 0.0
                accumulate(sums, prepared, j, rows, cols, result.columns["pwc"][rows], ~bad[rows],
                           model, receptors)
    offsets = solve(prepared, sums, opts.max_offset_wraps, _antenna_names(target_ms),
                    layout.chan_freq)
    for entry in offsets.solves:
        moved = {name: k for name, k in entry["k"].items() if k}
        log.info("n0 step (field %d, receptor %d, %s, mean cos mismatch %.3f): %s",
                 entry["field"], entry["receptor"], entry["method"], entry["mean_cos_mismatch"],
                 ", ".join(f"{n} {k:+d}" for n, k in moved.items()) or "no integer moved")
    return apply_offsets(prepared, offsets), offsets


def _antenna_names(ms: str):
    with tables.subtable(ms, "ANTENNA") as t:
        return [str(n) for n in t.getcol("NAME")]


def _write_outputs(tx: OutputTransaction, transfers, layout, columns, chunk_rows: int) -> Dict:
    """Every chunk of the target set corrected and staged; the sample counts."""
    counts = {"n_samples": 0, "flagged_before": 0, "not_calibrated": 0}
    for start, n, cols in _chunks(tx.target_ms, columns, chunk_rows):
        result = correct_chunk(transfers, layout, cols)
        before = cols["flag"] | cols["FLAG_ROW"][:, None, None]
        new_flag = before | result.uncalibrated[:, None, :]
        rows = np.arange(start, start + n)
        for method, column in result.columns.items():
            # the corrections are in the column already: one staged write per method
            tx.write_chunk(rows, column, {method: np.ones((n, column.shape[2]), np.complex64)},
                           new_flag)
        counts["n_samples"] += int(before.size)
        counts["flagged_before"] += int(before.sum())
        counts["not_calibrated"] += int((new_flag & ~before).sum())
    return counts


def _chunk_rows(opts: CalibrateOptions, target_ms: str, target_column: str) -> int:
    if int(opts.chunk_rows) > 0:
        return int(opts.chunk_rows)
    with tables.main_table(target_ms) as t:
        cell = t.getcell(target_column, 0) if t.nrows() else np.zeros((1, 1))
    return max(1, CHUNK_VISIBILITIES // int(np.prod(cell.shape)))


def _committed(tx: OutputTransaction) -> str:
    """What the target set holds when the run stops after its commit."""
    return (f"the run had finished writing: {tx.target_ms} holds the new "
            f"{', '.join(tx.outputs.values())} and FLAG; the report (and --caltable) did not "
            "finish; rerun the same command with --overwrite to redo it")


def _report(opts, methods, ref_ms, target_ms, outputs, transfers, counts, started) -> Dict:
    first = transfers[methods[0]]
    reports = {m: dataclasses.asdict(transfer_report(p, None, 0)) for m, p in transfers.items()}
    per_antenna = reports[methods[0]]["antennas"]
    return {
        "ref_ms": ref_ms, "target_ms": target_ms, "methods": methods, "outputs": outputs,
        "reference_table": {"path": first.table.path, "kind": first.table.kind, "methods": reports},
        "samples": counts,
        # diagnose reads the tracking section: per antenna, no per-baseline tracker here
        "tracking": {"setup": {"tracker": "reference-table"}, "baselines": [],
                     "antennas": [{"antenna": a["name"], "wraps": a["n_wraps"],
                                   "flagged_solutions": a["n_flagged"]} for a in per_antenna]},
        "verdict": {"skipped": "reference table: no reference-band visibilities are read"},
        "timings_s": {"total": round(time.perf_counter() - started, 4)},
    }


def calibrate_from_table(opts: CalibrateOptions, methods: List[str], ref_ms: str, target_ms: str,
                         started: float, prepared: PreparedInputs) -> Dict:
    """The whole ``--reference-table`` run: checks, transfer, column, table, report."""
    refuse_options(opts, methods)
    outputs, columns = check_inputs(opts, methods, ref_ms, target_ms)
    layout = read_layout(target_ms)
    # every check of the table (type, set, stations, solution interval) before anything is written
    transfers = {m: prepare_transfer(opts.reference_table, ref_ms, target_ms,
                                     wrap_counting=WRAP_COUNTING[m], antenna_map=opts.antenna_map)
                 for m in methods}
    chunk_rows = _chunk_rows(opts, target_ms, columns.target_data)
    offsets = None
    if columns.offset and "pwc" in transfers:   # --offset-model / --offset-reference-column
        transfers["pwc"], offsets = offset_step(transfers["pwc"], layout, columns, chunk_rows,
                                                opts, target_ms)
    tx = OutputTransaction(target_ms, outputs, columns.target_data, None, chunk_rows,
                           direct_writes=True)
    tx.check_space()
    tx.create_columns()
    counts = stage_and_commit(tx, lambda: _write_outputs(tx, transfers, layout, columns,
                                                         chunk_rows),
                              lambda: _committed(tx))
    try:
        return _finish(opts, methods, ref_ms, target_ms, outputs, transfers, counts, offsets,
                       columns, started, prepared)
    except BaseException as stop:
        stop.add_note(_committed(tx))
        raise


def _finish(opts, methods, ref_ms, target_ms, outputs, transfers, counts, offsets, columns,
            started, prepared) -> Dict:
    """After the commit: the report, --caltable, --export-uvfits."""
    report = _report(opts, methods, ref_ms, target_ms, outputs, transfers, counts, started)
    if offsets is not None:
        report["offsets"] = {"compared_with": columns.offset, "solves": offsets.solves}
    log.info("%d of %d target samples not calibrated by the table (no unflagged solution on "
             "either side), %d flagged before", counts["not_calibrated"], counts["n_samples"],
             counts["flagged_before"])
    report_path = Path(opts.report) if opts.report else Path(target_ms + ".hitops-calibrate.json")
    if opts.caltable:
        n_rows = write_target_table(transfers[methods[0]], opts.caltable, bool(opts.overwrite))
        report["caltable"] = {"path": str(opts.caltable), "kind": "Fringe Jones", "rows": n_rows,
                              "method": methods[0]}
        log.info("wrote the target-band Fringe Jones table %s (%d rows, %s)", opts.caltable,
                 n_rows, methods[0])
    finish_report(report, opts, ref_ms, target_ms, outputs, methods, prepared)
    report_path.write_text(json.dumps(report, indent=1))
    log.info("wrote %s to %s from reference table %s; report %s; %.2f s",
             ", ".join(outputs.values()), target_ms, opts.reference_table, report_path,
             time.perf_counter() - started)
    return report
