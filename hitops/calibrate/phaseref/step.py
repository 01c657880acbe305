"""``--calibrator-field``: the instrumental term after FPT, measured on a calibrator.

FPT leaves the target band with Phi_inst - R*phi_inst per station (the paper's
eq. for Phi_FPT): each band's instrumental phase and delay, slowly varying, the same
for every source.  With a calibrator observed in scans alternating with the target's,
source-frequency phase referencing (Rioja & Dodson 2011, AJ 141, 114) removes it:

1. per calibrator scan and spectral window, the FPT output (this run's staged
   column) is summed over the scan per baseline and channel, antenna phases are
   solved per channel from every baseline at once (a point source at the phase
   centre), and one phase (at the window's mean frequency) and one delay are fitted
   per antenna and parallel hand across the channels (hitops/kernels/phase_ref.py);
2. per antenna, phase (unwrapped from scan to scan) and delay are interpolated
   linearly in time between the calibrator scans (held before the first and after the
   last);
3. every other field's rows of the same column are multiplied by
   exp(-i (phi_p - phi_q)) exp(-2 pi i (nu_k - nu_0)(tau_p - tau_q)), hands p and q
   taken from the correlation (RL: p's R, q's L), and, on the parallel hands, by the
   conjugate phase of what the antenna model leaves on the calibrator's same baseline
   and channel over all its scans.  That part is real: the count tracker counts wraps
   per baseline, so a baseline whose reference phase starts a whole turn away from its
   antennas' difference carries 2 pi R_k m that no antenna term absorbs, the same on
   both fields (it assumes a point-like calibrator: any closure phase of its own would
   be copied onto the target).

Before the solve, every scan of both fields is multiplied by exp(-i 2 pi R_k N), N the
reference wrap count continued across the scan and field switches
(hitops/calibrate/phaseref/bridge.py): the count tracker restarts at every scan, and
without this each scan would carry its own 2 pi R_k n0.

The correction is written into the staged output column itself (the same
:class:`~hitops.calibrate.output.OutputTransaction`, committed or rolled back with the
transfer), so PWC_DATA holds the phase-referenced target: one column, as diagnose,
export and the recipes expect.  The calibrator's own rows stay as transferred, to be
checked.  Rows of an antenna with no solution on any calibrator scan are flagged.

docs/solutions.md, "The instrumental term", has the measurements and the limits.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ...errors import InputError
from ...io import read as msio
from ...io import tables
from ...io.ms_create import CORR_NAMES
from ...kernels.phase_ref import antenna_phasors, baseline_sums, model_residuals, phase_and_delay
from ...kernels.wideband import rotate_channels

log = logging.getLogger("hitops.calibrate")

#: iterations of the per-channel antenna phase solve (converged to < 1e-6 rad on the
#: noise-free pairs of tests/test_phase_referencing.py well before this)
SOLVE_ITERATIONS = 60


@dataclass(frozen=True)
class CalibratorField:
    """The calibrator of a run: its FIELD_ID in the target set and the fields it calibrates."""

    name: str
    field_id: int
    target_field_ids: Tuple[int, ...]


@dataclass(frozen=True)
class ScanSolution:
    """One calibrator scan's antenna phases and delays in one spectral window."""

    scan: int
    time: float                  # s, mean TIME of the scan's rows
    phase: np.ndarray            # (n_ant, n_hand) rad at the window's mean frequency
    delay: np.ndarray            # (n_ant, n_hand) s
    valid: np.ndarray            # (n_ant, n_hand) bool


@dataclass(frozen=True)
class WindowSolution:
    """Every calibrator scan of one target spectral window, and what the window is."""

    ddid: int
    spw: int
    freq: float                  # nu_0 (Hz): the window's mean channel frequency
    hands: Tuple[str, ...]       # the receptor letters of the parallel hands ('R', 'L')
    refant: int
    scans: List[ScanSolution]
    # what the antenna model leaves per calibrator baseline (ant1 * n_ant + ant2 in
    # ``baselines``), channel and hand, summed over every scan: its phase is removed
    # from the target's same baseline (hitops/kernels/phase_ref.py: model_residuals)
    baselines: np.ndarray = None        # (n_bl,) int64
    residual: np.ndarray = None         # (n_bl, n_chan, n_hand) complex128

    def at(self, times: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(phase, delay) (n_time, n_ant, n_hand) interpolated at ``times``; solved
        (n_ant, n_hand): antennas with at least one valid scan."""
        t = np.array([s.time for s in self.scans])
        phase = np.stack([s.phase for s in self.scans])
        delay = np.stack([s.delay for s in self.scans])
        valid = np.stack([s.valid for s in self.scans])
        n_ant, n_hand = phase.shape[1:]
        out_phase = np.zeros((times.size, n_ant, n_hand))
        out_delay = np.zeros_like(out_phase)
        for a in range(n_ant):
            for h in range(n_hand):
                ok = valid[:, a, h]
                if ok.any():
                    # the phase moves slowly from scan to scan: unwrap it in time
                    out_phase[:, a, h] = np.interp(times, t[ok], np.unwrap(phase[ok, a, h]))
                    out_delay[:, a, h] = np.interp(times, t[ok], delay[ok, a, h])
        return out_phase, out_delay, valid.any(axis=0)


def check_calibrator_field(run) -> Optional[CalibratorField]:
    """The run's calibrator (None without --calibrator-field), checked before anything is
    written: a field of TARGET_MS, with rows the transfer covers, and another field to
    apply it to."""
    name = run.opts.input.calibrator_field
    if not name:
        return None
    # the options it refuses (a robust tracker, the n0 step): hitops/calibrate/modes.py
    names = [str(n) for n in msio.read_subtable(run.target_ms, "FIELD", ["NAME"])["NAME"]]
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
    return CalibratorField(name, int(paired[name]), targets)


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


@dataclass(frozen=True)
class _WindowRows:
    """The rows of one target window this run wrote, split into calibrator and target."""

    cal_rows: np.ndarray
    cal_scan: np.ndarray
    cal_bl: np.ndarray           # baseline index of each calibrator row
    ant1: np.ndarray             # (n_bl,) of the calibrator's baselines
    ant2: np.ndarray
    target_rows: np.ndarray


def _window_rows(meta: Dict[str, np.ndarray], written: np.ndarray, ddid: int,
                 cal: CalibratorField, n_ant: int) -> _WindowRows:
    here = written & (meta["DATA_DESC_ID"] == ddid)
    cal_rows = np.flatnonzero(here & (meta["FIELD_ID"] == cal.field_id))
    target_rows = np.flatnonzero(here & np.isin(meta["FIELD_ID"], cal.target_field_ids))
    code = meta["ANTENNA1"][cal_rows].astype(np.int64) * n_ant + meta["ANTENNA2"][cal_rows]
    baselines, cal_bl = np.unique(code, return_inverse=True)
    return _WindowRows(cal_rows, meta["SCAN_NUMBER"][cal_rows], cal_bl.astype(np.int64),
                       baselines // n_ant, baselines % n_ant, target_rows)


def _solve_window(table, tx, column: str, rows: _WindowRows, group, hands, hand_corr,
                  refant: int, n_ant: int, ddid: int, times: np.ndarray,
                  chan_offset: np.ndarray) -> WindowSolution:
    """Every calibrator scan of one window solved (hitops/kernels/phase_ref.py);
    ``chan_offset``: each channel's frequency from the window's centre (Hz)."""
    scans = []
    residual = 0j
    for scan in np.unique(rows.cal_scan):
        pick = rows.cal_scan == scan
        read = msio.rows_reader(table, rows.cal_rows[pick])
        sums, counts = baseline_sums(read(column), tx.flags_now(table, rows.cal_rows[pick]),
                                     rows.cal_bl[pick], hand_corr, rows.ant1.size)
        g, solved = antenna_phasors(sums, counts, rows.ant1, rows.ant2, n_ant, refant,
                                    SOLVE_ITERATIONS)
        phase, delay, valid = phase_and_delay(g, solved, chan_offset)
        residual = residual + model_residuals(sums, counts, rows.ant1, rows.ant2, phase, delay,
                                              valid, chan_offset)
        scans.append(ScanSolution(int(scan), float(np.mean(times[rows.cal_rows[pick]])),
                                  phase, delay, valid))
    return WindowSolution(ddid, group.pair.tgt.spw, group.pair.tgt.freq, hands, refant, scans,
                          rows.ant1.astype(np.int64) * n_ant + rows.ant2, residual)


def _baseline_factors(solution: WindowSolution, ant1, ant2, corr_hands, n_ant: int):
    """(n_row, n_chan, n_corr) complex64: exp(-i x the calibrator's model residual phase)
    of each row's baseline on its parallel hands; 1 for cross hands and baselines the
    calibrator did not observe."""
    n_chan = solution.residual.shape[1]
    out = np.ones((ant1.size, n_chan, corr_hands.shape[0]), np.complex64)
    pos = np.searchsorted(solution.baselines, ant1.astype(np.int64) * n_ant + ant2)
    pos = np.minimum(pos, solution.baselines.size - 1)
    seen = solution.baselines[pos] == ant1.astype(np.int64) * n_ant + ant2
    for c, (h1, h2) in enumerate(corr_hands):
        if h1 < 0 or h1 != h2:
            continue
        res = solution.residual[pos[seen], :, h1]
        out[seen, :, c] = np.where(np.abs(res) > 0, np.conj(res) / np.maximum(np.abs(res), 1e-300),
                                   1.0)
    return out


def _apply_window(table, tx, column: str, rows: np.ndarray, meta, solution: WindowSolution,
                  corr_hands: np.ndarray, chan_offset: np.ndarray, block: int,
                  n_ant: int) -> int:
    """The interpolated correction applied to the target rows of one window, block by
    block, written through the transaction's own write path; rows touching an antenna
    without a solution are flagged.  Returns the number of rows flagged."""
    n_flagged = 0
    for start in range(0, rows.size, block):
        part = rows[start:start + block]
        phase, delay, solved = solution.at(meta["TIME"][part])
        a1, a2 = meta["ANTENNA1"][part][:, None], meta["ANTENNA2"][part][:, None]
        i = np.arange(part.size)[:, None]
        known = (corr_hands[:, 0] >= 0) & (corr_hands[:, 1] >= 0)
        h1 = np.where(known, corr_hands[:, 0], 0)[None, :]
        h2 = np.where(known, corr_hands[:, 1], 0)[None, :]
        ok = known[None, :] & solved[a1, h1] & solved[a2, h2]
        dphi = phase[i, a1, h1] - phase[i, a2, h2]
        dtau = delay[i, a1, h1] - delay[i, a2, h2]
        phasor = np.where(ok, np.exp(-1j * dphi), 1.0 + 0j)
        read = msio.rows_reader(table, part)
        rotated = rotate_channels(read(column), phasor, np.where(ok, dtau, 0.0), chan_offset)
        arrays = {column: rotated * _baseline_factors(solution, a1[:, 0], a2[:, 0], corr_hands,
                                                      n_ant)}
        new_flag = None
        if not ok.all():
            new_flag = tx.flags_now(table, part) | ~ok[:, None, :]
            n_flagged += int((~ok).any(axis=1).sum())
        tx.restage(part, arrays, new_flag)
    return n_flagged


def _refant(run, names: List[str], cal_ant: np.ndarray) -> int:
    """--refant's first station present on the calibrator, else the one in most rows."""
    present = set(np.unique(cal_ant).tolist())
    for code in (run.opts.tracking.refant or "").split(","):
        if code.strip() in names and names.index(code.strip()) in present:
            return names.index(code.strip())
    return int(np.bincount(cal_ant, minlength=len(names)).argmax())


def _bridge_window(table, tx, column: str, rows: np.ndarray, counts: np.ndarray, group,
                   block: int) -> None:
    """Every scan's rows times exp(-i 2 pi R_k N) (hitops/calibrate/phaseref/bridge.py):
    as a phase at nu_0 and a delay N / nu_ref, the per-channel transfer's own form."""
    if group.channels is not None:
        ratio, centre = group.channels.ratio, group.channels.tgt_centre
    else:
        ratio, centre = group.ratio, group.pair.tgt.freq
    chan_offset = np.asarray(group.pair.tgt.chan_freq) - centre
    moved = rows[(counts != 0).any(axis=1)]
    counts = counts[(counts != 0).any(axis=1)]
    for start in range(0, moved.size, block):
        part, n = moved[start:start + block], counts[start:start + block]
        read = msio.rows_reader(table, part)
        phasor = np.exp(-2j * np.pi * ratio * n)
        arrays = {column: rotate_channels(read(column), phasor, n * (ratio / centre),
                                          chan_offset)}
        tx.restage(part, arrays)


def _reference_window(run, tx, table, column, meta, cal, ddid, groups, bridge) -> Dict:
    """One target window of one staged column: bridged, solved on the calibrator,
    applied to the other fields; its report entry."""
    from .report import window_report

    group = groups[0]
    names = group.antenna_names
    rows = _window_rows(meta, tx.rows_written, ddid, cal, len(names))
    hands, hand_corr, corr_hands = _hands(group.pair.tgt.corr)
    if not hands:
        raise InputError(f"--calibrator-field {cal.name}: spectral window "
                         f"{group.pair.tgt.spw} of {run.target_ms} has no parallel-hand "
                         "correlation (RR, LL, XX, YY) to solve on")
    both = np.union1d(rows.cal_rows, rows.target_rows)
    _bridge_window(table, tx, column, both, bridge.counts, group, run.chunk_rows)
    refant = _refant(run, names, np.concatenate([meta["ANTENNA1"][rows.cal_rows],
                                                 meta["ANTENNA2"][rows.cal_rows]]))
    chan_offset = np.asarray(group.pair.tgt.chan_freq) - group.pair.tgt.freq
    solution = _solve_window(table, tx, column, rows, group, hands, hand_corr, refant,
                             len(names), ddid, meta["TIME"], chan_offset)
    n_flagged = _apply_window(table, tx, column, rows.target_rows, meta, solution,
                              corr_hands, chan_offset, run.chunk_rows, len(names))
    entry = window_report(solution, names, rows.target_rows.size, n_flagged)
    entry["switches"] = {"scan_starts": bridge.n_scan_starts,
                         "largest_step_deg": round(bridge.largest_step_deg, 3),
                         "steps_over_90_deg": bridge.n_risky}
    return entry


def phase_reference(run, tx, cal: Optional[CalibratorField]) -> Optional[Dict]:
    """Bridge the scans, solve on the calibrator's, apply to the other fields' rows, in
    every staged output column of ``tx``; the report's entry (None without a calibrator)."""
    from .bridge import switch_counts
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
                   "target_field_ids": list(cal.target_field_ids), "methods": {}}
    with tables.main_table(run.target_ms) as table:
        meta = {c: table.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "FIELD_ID",
                                             "DATA_DESC_ID", "SCAN_NUMBER")}
        bridges = {}
        for ddid, groups in windows.items():
            if groups[0].pair.tgt.field != cal.name:
                continue     # a window the calibrator was not observed in
            n_ant = len(groups[0].antenna_names)
            rows = _window_rows(meta, tx.rows_written, ddid, cal, n_ant)
            bridges[ddid] = switch_counts(run, groups, meta,
                                          np.union1d(rows.cal_rows, rows.target_rows))
        for method, column in tx.staging.items():
            entry["methods"][run.outputs[method]] = [
                _reference_window(run, tx, table, column, meta, cal, ddid, windows[ddid],
                                  bridge) for ddid, bridge in sorted(bridges.items())]
    log_summary(entry)
    return entry


def settle_n0_warnings(report: Dict, cal: CalibratorField) -> None:
    """The target fields' "no n0 step" warnings answered: their per-scan constants were
    carried across the scans and their per-baseline one removed with the calibrator's."""
    for entry in report.get("groups", []):
        step = entry.get("offset_step", {})
        if entry.get("field") != cal.name and step.get("warning"):
            step["warning"] = None
            step["note"] = (f"no n0 step: the per-scan 2 pi eps n0 were carried across the scans "
                            f"and the per-baseline constant removed with {cal.name}'s "
                            "(--calibrator-field)")
