"""``--calibrator-field``: the instrumental term after FPT, measured on a calibrator.

FPT leaves the target band with Phi_inst - R*phi_inst per station (the paper's
eq. for Phi_FPT): each band's instrumental phase and delay, slowly varying, the same
for every source.  With a calibrator observed in scans alternating with the target's,
source-frequency phase referencing (Rioja & Dodson 2011, AJ 141, 114) removes it.
Every scan also keeps 2 pi R_k m, one integer per scan and baseline: the reference wrap
count starts afresh at every scan, and a slew of a minute is too long to carry it across
(the 86-GHz phase moves by radians meanwhile).  Per target window:

1. per calibrator scan, the FPT output (this run's staged column) divided by the
   calibrator's model (``--calibrator-model-column``, MODEL_DATA when the set has it) is
   summed per baseline and channel; each scan's integer m per baseline and hand comes
   from the scan-to-scan change of its delay across the window (m / nu_ref: 11.6 ps per
   wrap at 86 GHz) and is removed (:mod:`.solve`); with one channel there is no delay to
   see and the count is carried across the switches instead (:mod:`.bridge`);
2. antenna phases are solved per channel from every baseline at once, one phase (at the
   window's centre) and one delay fitted per antenna and parallel hand, and what the
   antenna model leaves per baseline (over all scans) kept: the first scan's integers,
   which need not close (hitops/kernels/phase_ref.py);
3. per antenna, phase (unwrapped from scan to scan) and delay are interpolated linearly
   in time between the calibrator scans (held before the first and after the last) and
   removed from every other field's rows of the same column, with the per-baseline
   residual; then each target scan's own integer j is the delay of what is left, in
   wraps, and 2 pi R_k j is removed too (:mod:`.apply`).

Each window is done in three passes over the target set in the run's chunks
(:mod:`.passes`: the calibrator's sums; the calibrator's integers removed and the
target corrected; the target's integers removed), inside the memory budget: only
per-scan sums are kept between chunks.

The correction is written into the staged output column itself (the same
:class:`~hitops.calibrate.output.OutputTransaction`, committed or rolled back with the
transfer), so PWC_DATA holds the phase-referenced target: one column, as diagnose,
export and the recipes expect (on a processing set the same passes read and rewrite
each method's staged data group: :mod:`hitops.calibrate.set_rows`,
:class:`~hitops.calibrate.output_msv4.DataGroupTransaction`).  The calibrator's rows
keep the transfer's output with their integers removed, to be checked.  Rows of an antenna with no solution on any
calibrator scan are flagged.

docs/solutions.md, "The instrumental term", has the measurements and the limits.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ...errors import ColumnError, InputError
from ...io import read as msio
from ...io.ms_create import CORR_NAMES
from . import apply as target_side
from . import passes
from . import solve as calibrator_side
from .passes import WindowPass
from ..set_rows import open_set_rows, target_sources
from .solve import CalibratorIntegers, WindowFrame

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class CalibratorField:
    """The calibrator of a run: its FIELD_ID in the target set, the fields it calibrates,
    and the column of TARGET_MS holding its model (None: a point at the phase centre)."""

    name: str
    field_id: int
    target_field_ids: Tuple[int, ...]
    model_column: Optional[str] = None

    @property
    def model_label(self) -> str:
        """What the report says of the model used."""
        return self.model_column or "point (a point source at the phase centre)"


def _model_column(run, name: str) -> Optional[str]:
    """--calibrator-model-column resolved: 'point' -> None; unset -> MODEL_DATA when
    TARGET_MS has it (CASA's convention: setjy, ft, wsclean -predict write it), else None;
    a named column must exist."""
    given = run.opts.input.calibrator_model_column
    if given == "point":
        return None
    present = msio.column_names(run.target_ms)
    if given is None:
        return "MODEL_DATA" if "MODEL_DATA" in present else None
    if given not in present:
        raise ColumnError(f"--calibrator-model-column {given}: {run.target_ms} has no such "
                          "column; give a model column it has (e.g. MODEL_DATA) or 'point'")
    return given


def check_calibrator_field(run) -> Optional[CalibratorField]:
    """The run's calibrator (None without --calibrator-field), checked before anything is
    written: a field of TARGET_MS, with rows the transfer covers, and another field to
    apply it to."""
    name = run.opts.input.calibrator_field
    if not name:
        return None
    # the options the calibrator mode refuses (the n0 step; the model column without a
    # calibrator): hitops/calibrate/modes.py; what needs the sets is checked here
    one_channel = any(g.channels is None or not g.channels.across_channels for g in run.groups)
    if one_channel and run.opts.tracking.tracker != "count":
        raise InputError(f"--calibrator-field {name} on a one-channel target window carries "
                         "the count tracker's per-scan counts across the field switches "
                         "(no delay across the window to find each scan's integer from; "
                         f"docs/solutions.md): drop --tracker {run.opts.tracking.tracker}")
    names = [str(n) for n in run.tgt_meta.fields.names]
    if name not in names:
        raise InputError(f"--calibrator-field {name}: no such field in {run.target_ms} "
                         f"(FIELD::NAME holds {', '.join(names) or 'nothing'}); give one of "
                         "those names")
    paired = {g.pair.tgt.field: g.pair.tgt.key[0] for g in run.groups}
    if name not in paired:
        raise InputError(f"--calibrator-field {name}: {run.target_ms} has no calibrator scans "
                         f"to solve on (no rows of field {name} that REF_MS observed at the same "
                         "times); give the field observed in scans between the target's")
    targets = tuple(sorted({fid for f, fid in paired.items() if f != name}))
    if not targets:
        raise InputError(f"--calibrator-field {name}: it is the only field of {run.target_ms} "
                         "with calibrated rows, so there is no target to apply it to; name the "
                         "calibrator, not the target")
    cal = CalibratorField(name, int(paired[name]), targets, _model_column(run, name))
    check_model(run, cal)
    return cal


def _hands(corr: Tuple[int, ...]) -> Tuple[Tuple[str, ...], np.ndarray, np.ndarray]:
    """(parallel-hand letters, their correlation index, (n_corr, 2) hand index of each
    correlation's two receptors, -1 for a product hitops does not know)."""
    # each product's two receptors are the letters of its casacore name (RL: R and L)
    pairs = [tuple(CORR_NAMES[int(code)]) if int(code) in CORR_NAMES else None
             for code in corr]
    names = [p[0] for p in pairs if p and p[0] == p[1]]
    hand_corr = np.array([i for i, p in enumerate(pairs) if p and p[0] == p[1]], np.int64)
    index = np.full((len(corr), 2), -1, np.int64)
    for i, p in enumerate(pairs):
        if p and p[0] in names and p[1] in names:
            index[i] = names.index(p[0]), names.index(p[1])
    return tuple(names), hand_corr, index


def _refant(run, names: List[str], cal_ant: np.ndarray) -> int:
    """--refant's first station present on the calibrator, else the one in most rows."""
    present = set(np.unique(cal_ant).tolist())
    for code in (run.opts.tracking.refant or "").split(","):
        if code.strip() in names and names.index(code.strip()) in present:
            return names.index(code.strip())
    return int(np.bincount(cal_ant, minlength=len(names)).argmax())


def integer_rule(frame: WindowFrame) -> str:
    """How a window's per-scan integers are found: "delay" (each scan's from its delay
    across the window) with several channels, "carried" (the count carried across the
    switches, which needs slews shorter than the reference band's coherence time) with
    one, where there is no delay to see."""
    return "delay" if frame.chan_offset.size > 1 else "carried"


def _integer_summary(integers: np.ndarray, margin: np.ndarray, valid: np.ndarray) -> Dict:
    """How many scan x baseline x hand integers were not 0, and the smallest margin."""
    measured = valid & np.isfinite(margin)
    return {"decided": int(valid.sum()), "nonzero": int((integers[valid] != 0).sum()),
            "min_margin": round(float(margin[measured].min()), 4) if measured.any() else None}


def check_model(run, cal: CalibratorField) -> None:
    """The calibrator's model checked before anything is written: no zeros where the
    calibrator is (nothing to divide by), and a resolved one (phases not all 0) only
    with the reference band's model too (FPT leaves Psi_k - R_k psi of the calibrator's
    own phases otherwise).  Read chunk by chunk (the run's rows per chunk)."""
    if cal.model_column is None:
        return
    resolved, zero_scans = False, set()
    with open_set_rows(run.target_ms, target_sources(run)) as set_rows:
        n_rows, step = set_rows.n_rows, max(run.chunk_rows, 1)
        for start in range(0, n_rows, step):
            n = min(step, n_rows - start)
            rows = start + np.flatnonzero(
                set_rows.index(["FIELD_ID"], start, n)["FIELD_ID"] == cal.field_id)
            if not rows.size:
                continue
            read = set_rows.reader(rows)
            model = read(cal.model_column)
            zero = (np.abs(model) == 0).any(axis=(1, 2))
            zero_scans.update(np.unique(read("SCAN_NUMBER")[zero]).tolist())
            resolved |= bool(np.abs(np.angle(model[~zero])).max(initial=0.0) > 1e-6)
    if zero_scans:
        raise InputError(f"--calibrator-field {cal.name}: {cal.model_column} of {run.target_ms} "
                         f"is zero on calibrator scan(s) {', '.join(map(str, sorted(zero_scans)))} "
                         "(no model there to divide by); fill it (CASA setjy/ft, wsclean "
                         "-predict) or give --calibrator-model-column point")
    if resolved and run.columns.ref_model is None:
        raise InputError(f"--calibrator-field {cal.name}: {cal.model_column} of "
                         f"{run.target_ms} holds a resolved calibrator (non-zero phases), "
                         "whose reference-band phases the transfer must remove too: add "
                         f"--ref-model-column {cal.model_column} (REF_MS's model), or "
                         "--calibrator-model-column point")


@dataclass(frozen=True)
class CarriedCounts:
    """A one-channel window's continued counts (:mod:`.bridge`) and the rows they are of:
    the window's calibrator and target rows, ascending."""

    rows: np.ndarray
    switches: object             # bridge.SwitchCounts


def _carried_counts(run, set_rows, tx, window: WindowPass, groups) -> CarriedCounts:
    """The continued counts of every calibrator and target row of a one-channel window,
    from their index columns read chunk by chunk."""
    from .bridge import switch_counts

    parts = [(c.cal, c.target) for c in window.chunks(set_rows, tx.rows_written)]
    both = [p for pair in parts for p in pair]
    rows = np.concatenate([p.rows for p in both]) if both else np.zeros(0, np.int64)
    order = np.argsort(rows, kind="stable")
    meta = {"TIME": np.concatenate([p.time for p in both])[order] if both else np.zeros(0),
            **{name: (np.concatenate([getattr(p, attr) for p in both])[order] if both
                      else np.zeros(0, np.int64))
               for name, attr in (("ANTENNA1", "ant1"), ("ANTENNA2", "ant2"),
                                  ("FIELD_ID", "field"))}}
    return CarriedCounts(rows[order], switch_counts(run, groups, meta, np.arange(rows.size)))


def _calibrator_integers(cal: CalibratorField, found: passes.CalibratorScans, frame,
                         names: List[str], spw: int, carried: bool) -> CalibratorIntegers:
    """Each calibrator scan's integers, checked (zeros where the count was carried)."""
    n_ant = len(names)
    if carried:
        zero = np.zeros(found.counts.shape[:2] + found.counts.shape[3:], np.int64)
        return CalibratorIntegers(zero, np.full(zero.shape, 0.5), "carried")
    integers = calibrator_side.calibrator_integers(found.times, found.sums, found.counts, frame)
    calibrator_side.check_decided(integers, found.scan_numbers, [
        f"{names[p]}-{names[q]}" for p, q in zip(found.ant1(n_ant), found.ant2(n_ant))],
        cal.name, spw)
    return integers


def _apply_pass(set_rows, tx, column: str, window: WindowPass, found: passes.CalibratorScans,
                integers: Optional[CalibratorIntegers], solution, corr_hands, frame,
                n_ant: int) -> Tuple[int, passes.TargetLeft]:
    """The second pass: each calibrator scan's integers removed from its rows (``integers``;
    None: the count was carried), the interpolated correction applied to the target's;
    (rows flagged, what is left on the target)."""
    hand_corr = np.array([c for c, (h1, h2) in enumerate(corr_hands) if h1 >= 0 and h1 == h2],
                         np.int64)
    left = passes.TargetLeft(window.chunk_rows, (n_ant * n_ant, frame.chan_offset.size,
                                                 hand_corr.size))
    n_flagged = 0
    for chunk in window.chunks(set_rows, tx.rows_written):
        if integers is not None and chunk.cal.rows.size:
            bl = np.searchsorted(found.baselines, chunk.cal.code(n_ant))
            target_side.remove_integers(set_rows, tx, column, chunk.cal.rows, target_side.row_counts(
                chunk.cal.scan, found.scans, bl, integers.integers, corr_hands), frame,
                window.chunk_rows)
        if chunk.target.rows.size:
            flagged, flags, rotated = target_side.apply_chunk(set_rows, tx, column, chunk.target,
                                                              solution, corr_hands, frame, n_ant)
            n_flagged += flagged
            left.add(chunk.target, rotated, flags, hand_corr, n_ant)
    return n_flagged, left


def _target_pass(set_rows, tx, column: str, window: WindowPass, found, corr_hands, frame,
                 n_ant: int) -> int:
    """The third pass: each target scan's integer removed, the undecided ones' rows flagged;
    the number of rows flagged."""
    n_undecided = 0
    for chunk in window.chunks(set_rows, tx.rows_written):
        t = chunk.target
        if not t.rows.size:
            continue
        code = t.code(n_ant)
        target_side.remove_integers(set_rows, tx, column, t.rows, target_side.row_counts(
            t.scan, found.scans, code, found.integers, corr_hands), frame, window.chunk_rows)
        undecided = target_side.row_counts(t.scan, found.scans, code, found.undecided,
                                           corr_hands)
        n_undecided += target_side.flag_rows(set_rows, tx, t.rows, undecided, window.chunk_rows)
    return n_undecided


def _reference_window(run, tx, set_rows, column, cal, window: WindowPass,
                      carried: Optional[CarriedCounts]) -> Dict:
    """One target window of one staged column, in passes over the run's chunks: each
    calibrator scan's integers found, solved on the calibrator, applied to the other
    fields with each target scan's own integer; its report entry."""
    from .report import window_report

    group = window.groups[0]
    names, n_ant, spw = group.antenna_names, len(group.antenna_names), group.pair.tgt.spw
    frame = WindowFrame.of_group(group)
    hands, hand_corr, corr_hands = _hands(group.pair.tgt.corr)
    if not hands:
        raise InputError(f"--calibrator-field {cal.name}: spectral window {spw} of "
                         f"{run.target_ms} has no parallel-hand correlation (RR, LL, XX, YY) "
                         "to solve on")
    if carried is not None:    # one channel: the count carried across the switches
        target_side.remove_integers(set_rows, tx, column, carried.rows, carried.switches.counts,
                                    frame, window.chunk_rows)
    found = passes.calibrator_pass(set_rows, tx, column, window, hand_corr, cal.model_column,
                                   n_ant, frame.chan_offset.size)
    integers = _calibrator_integers(cal, found, frame, names, spw, carried is not None)
    ant1, ant2 = found.ant1(n_ant), found.ant2(n_ant)
    refant = _refant(run, names, np.concatenate([ant1, ant2]))
    solution = calibrator_side.solve_window(found.scans, found.times, found.sums, found.counts,
                                            ant1, ant2, frame, integers, refant, n_ant,
                                            (window.ddid, spw, hands))
    if not any(scan.valid.any() for scan in solution.scans):
        raise InputError(f"--calibrator-field {cal.name}: no calibrator scan of spectral window "
                         f"{spw} has unflagged data in both bands (REF_MS {run.ref_ms}, "
                         f"TARGET_MS {run.target_ms}) to solve on; unflag it or name a "
                         "calibrator observed in both bands")
    n_flagged, left = _apply_pass(set_rows, tx, column, window, found,
                                  None if carried is not None else integers, solution,
                                  corr_hands, frame, n_ant)
    entry = window_report(solution, names, left.n_rows, n_flagged)
    entry["scans"] = [dict(s, scan_number=n) for s, n in zip(entry["scans"], found.scan_numbers)]
    entry["calibrator_model"] = cal.model_label
    entry["integers"] = {"rule": integers.rule, "calibrator": _integer_summary(
        integers.integers, integers.margin, found.counts.sum(axis=2) > 0)}
    if carried is not None:
        switches = carried.switches
        entry["switches"] = {"scan_starts": switches.n_scan_starts,
                             "largest_step_deg": round(switches.largest_step_deg, 3),
                             "steps_over_90_deg": switches.n_risky}
        return entry
    t_scans, t_times, t_sums, t_counts = left.finish()
    found_t = target_side.target_integers(t_scans, t_times, t_sums, t_counts, frame, n_ant)
    n_undecided = _target_pass(set_rows, tx, column, window, found_t, corr_hands, frame, n_ant)
    entry["integers"]["target"] = dict(
        _integer_summary(found_t.integers, found_t.margin, found_t.valid),
        undecided_scans=int(found_t.undecided.sum()), rows_flagged=n_undecided)
    if n_undecided:
        log.warning("--calibrator-field %s: %d target scan x baseline x hand series of window "
                    "%d had no clear integer (the delay left lay more than %.2f wraps from "
                    "every one); their %d rows are flagged", cal.name,
                    int(found_t.undecided.sum()), spw, 0.5 - target_side.MIN_TARGET_MARGIN,
                    n_undecided)
    return entry


def phase_reference(run, tx, cal: Optional[CalibratorField]) -> Optional[Dict]:
    """Each scan's integers removed, solved on the calibrator's scans, applied to the other
    fields' rows, in every staged output column of ``tx``, in passes over the run's chunks;
    the report's entry (None without a calibrator)."""
    from .report import log_summary

    if cal is None:
        return None
    windows: Dict[int, List] = {}
    for group in sorted(run.groups, key=lambda g: g.pair.tgt.field != cal.name):
        windows.setdefault(group.pair.tgt.key[1], []).append(group)
    for ddid, groups in windows.items():
        if groups[0].pair.tgt.field != cal.name:
            log.warning("--calibrator-field %s: no calibrator rows in target spectral window %d; "
                        "its rows are left as transferred", cal.name, groups[0].pair.tgt.spw)
    entry: Dict = {"calibrator_field": cal.name, "field_id": cal.field_id,
                   "target_field_ids": list(cal.target_field_ids),
                   "calibrator_model": cal.model_label, "methods": {}}
    with open_set_rows(run.target_ms, target_sources(run), tx) as set_rows:
        plan: Dict[int, Tuple[WindowPass, Optional[CarriedCounts]]] = {}
        for ddid, groups in sorted(windows.items()):
            if groups[0].pair.tgt.field != cal.name:
                continue     # a window the calibrator was not observed in
            window = WindowPass(int(ddid), cal.field_id, cal.target_field_ids, groups,
                                max(int(run.chunk_rows), 1))
            carried = None
            if integer_rule(WindowFrame.of_group(groups[0])) != "delay":
                carried = _carried_counts(run, set_rows, tx, window, groups)
            plan[ddid] = (window, carried)
        for method, column in tx.staging.items():
            entry["methods"][run.outputs[method]] = [
                _reference_window(run, tx, set_rows, column, cal, window, carried)
                for window, carried in plan.values()]
    log_summary(entry)
    return entry


def settle_n0_warnings(report: Dict, cal: CalibratorField) -> None:
    """The target fields' "no n0 step" warnings answered: their per-scan constants were
    carried across the scans and their per-baseline one removed with the calibrator's."""
    for entry in report.get("groups", []):
        step = entry.get("offset_step", {})
        if entry.get("field") != cal.name and step.get("warning"):
            step["warning"] = None
            step["note"] = (f"no n0 step: each scan's 2 pi R_k n was solved on {cal.name} and "
                            "the target (--calibrator-field) and the per-baseline constant "
                            f"removed with {cal.name}'s")
