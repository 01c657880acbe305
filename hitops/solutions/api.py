"""transfer_table: a reference band's calibration table in, a target-band Fringe Jones table out.

Stages, each with its type: ``read_solutions`` (REF_MS's table -> ``SolutionTable``,
refused when solved on another set) -> ``unwrap_window`` per reference window
(``UnwrappedWindow``; ``check_interval`` refuses a table whose phase moves by more
than pi between solutions) -> ``transfer_window`` per target window and field
(``TargetWindow``) -> ``write_fringe_table``.  Every check runs before anything is
written; the table appears whole or not at all.
"""

from __future__ import annotations

import logging
from pathlib import Path
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from ..io.match import pair_antennas, parse_antenna_map
from ..io.stations import stations_of
from .errors import TableMismatchError, TransferOptionError
from .read import SolutionTable, WindowSolutions, _ms_time_range, read_solutions
from .transfer import TargetWindow, UnwrappedWindow, check_interval, transfer_window, unwrap_window
from .wraps import UNBRIDGED
from ..io.read import read_row_columns
from ..io.metadata import SetMetadata, read_metadata

log = logging.getLogger("hitops.solutions")


@dataclass(frozen=True)
class AntennaSummary:
    name: str
    n_solutions: int          # unflagged solutions, all windows and receptors of the reference
    n_flagged: int            # solution slots without an unflagged solution
    n_wraps: int              # wraps counted (sum of |steps| of the count)
    max_residual_rad: float   # largest |bridged residual|: how close to the Itoh limit


@dataclass(frozen=True)
class RefantChange:
    time: float
    spw: int
    field: int
    from_antenna: str
    to_antenna: str
    bridged: bool             # re-referred through antennas solved on both sides


@dataclass(frozen=True)
class TransferReport:
    table: Optional[str]          # the target table written, None when none was
    reference_table: str
    kind: str
    wrap_counting: bool
    reference_freq_hz: Tuple[float, ...]   # per reference window used: the table's CHAN_FREQ
    target_centres_hz: Tuple[float, ...]   # per target window written
    n_rows: int
    n_segments: int                        # scans/gaps after which the count restarts its branch
    common_refant: Tuple[str, ...]         # per reference window used: the frame all are re-referred to
    antennas: Tuple[AntennaSummary, ...]
    refant_changes: Tuple[RefantChange, ...]


def _target_windows(target_ms: str, meta: SetMetadata):
    """(spw id, centre Hz) of every spectral window the target's data use; field names."""
    windows = []
    for spw in sorted({d.window for d in meta.data_descriptions}):
        freq = meta.windows[spw].chan_freq
        windows.append((spw, 0.5 * (freq.min() + freq.max())))
    fields = list(meta.fields.names)
    rows = read_row_columns(target_ms, ["ANTENNA1", "ANTENNA2"])   # MSv2 or a processing set
    return windows, fields, rows["ANTENNA1"], rows["ANTENNA2"]


def _check_overlap(table: SolutionTable, target_ms: str) -> None:
    """The target set must be the other band of the same observation: its times meet the solutions'."""
    t_min, t_max, interval = _ms_time_range(target_ms)
    times = np.concatenate([w.times for w in table.windows])
    slack = interval + 1.0
    if not np.any((times >= t_min - slack) & (times <= t_max + slack)):
        raise TableMismatchError(
            f"TARGET_MS '{target_ms}' ({t_min:.1f}-{t_max:.1f} s, MJD seconds) does not overlap the "
            f"solutions of reference table '{table.path}' ({times.min():.1f}-{times.max():.1f} s); "
            "the two sets must be the two bands of one observation")


def _reference_windows(table: SolutionTable, ref_spw: Optional[int]) -> Dict[str, WindowSolutions]:
    """The reference window used for each field: ``ref_spw``, else the best-solved one."""
    chosen: Dict[str, WindowSolutions] = {}
    spws = sorted({w.spw for w in table.windows})
    if ref_spw is not None and ref_spw not in spws:
        raise TransferOptionError(f"reference table '{table.path}' has no solutions in spectral "
                                  f"window {ref_spw}; it has {spws}")
    for w in table.windows:
        if ref_spw is not None and w.spw != ref_spw:
            continue
        best = chosen.get(w.field_name)
        if best is None or w.valid.sum() > best.valid.sum():
            chosen[w.field_name] = w
    return chosen


def _on_target_antennas(window: TargetWindow, ref_to_tgt: np.ndarray, n_ant_t: int) -> TargetWindow:
    """The same solutions indexed by the target's ANTENNA rows (missing stations flagged)."""
    def pick(values, fill):
        out = np.full((values.shape[0], n_ant_t) + values.shape[2:], fill, values.dtype)
        for ref_ant, tgt_ant in enumerate(ref_to_tgt):
            if tgt_ant >= 0:
                out[:, tgt_ant] = values[:, ref_ant]
        return out

    refant = np.where(window.refant >= 0,
                      ref_to_tgt[np.clip(window.refant, 0, None)], -1).astype(np.int32)
    return TargetWindow(window.spw, window.field, window.centre_hz, window.times, window.scan,
                        pick(window.phase, 0.0), pick(window.delay_s, 0.0), pick(window.rate, 0.0),
                        pick(window.valid, False), refant)


def _wrap_steps(u: UnwrappedWindow, ant: int) -> int:
    """Wraps counted on one antenna: the sum of |steps| of its count over its valid solutions."""
    total = 0
    for rec in range(u.wraps.shape[2]):
        counts = u.wraps[:, ant, rec][u.source.valid[:, ant, rec]]
        total += int(np.abs(np.diff(counts)).sum())
    return total


def _summaries(table: SolutionTable, unwrapped: Tuple[UnwrappedWindow, ...]):
    out = []
    for ant, name in enumerate(table.antenna_names):
        valid = sum(int(u.source.valid[:, ant].sum()) for u in unwrapped)
        slots = sum(u.source.valid[:, ant].size for u in unwrapped)
        res = [np.nanmax(np.abs(u.residual[:, ant])) for u in unwrapped
               if np.isfinite(u.residual[:, ant]).any()]
        out.append(AntennaSummary(name, valid, slots - valid, sum(_wrap_steps(u, ant) for u in unwrapped),
                                  float(max(res)) if res else 0.0))
    return tuple(out)


def _first_refant(table: SolutionTable, u: UnwrappedWindow) -> str:
    """The reference antenna of the window's first solution: the frame of every series."""
    known = u.source.refant[u.source.refant >= 0]
    return table.antenna_names[known[0]] if known.size else ""


def _refant_changes(table: SolutionTable, unwrapped: Tuple[UnwrappedWindow, ...]):
    changes = []
    names = table.antenna_names
    for u in unwrapped:
        w = u.source
        for s in np.flatnonzero(u.switch.max(axis=1) > 0):
            before = w.refant[:s][w.refant[:s] >= 0]
            changes.append(RefantChange(float(w.times[s]), w.spw, w.field,
                                        names[before[-1]] if before.size else "?",
                                        names[w.refant[s]],
                                        bool(np.all(u.switch[s] != UNBRIDGED))))
    return tuple(changes)


@dataclass(frozen=True)
class PreparedTransfer:
    """Every check passed and every window transferred; nothing written yet.

    ``targets``: one :class:`TargetWindow` per (reference field, target window), indexed
    by TARGET_MS's ANTENNA rows; what the target table holds and what ``hitops
    calibrate --reference-table`` applies to the target's column.
    """

    table: SolutionTable
    target_ms: str
    wrap_counting: bool
    unwrapped: Tuple[UnwrappedWindow, ...]
    targets: Tuple[TargetWindow, ...]
    target_centres_hz: Tuple[float, ...]
    n_ant_target: int


@dataclass(frozen=True)
class PairedTable:
    """A reference table read and checked against both sets, before any transfer: what every
    method's transfer of it starts from (:func:`prepare_transfers`)."""

    table: SolutionTable
    target_ms: str
    windows: Tuple[Tuple[int, float], ...]      # (target spw, centre Hz) of the target's data
    target_fields: Tuple[str, ...]
    ref_to_tgt: np.ndarray                      # (n_ant_ref,) target ANTENNA row or -1
    n_ant_target: int
    by_field: Dict[str, WindowSolutions]        # the reference window used for each field
    common: Tuple[str, ...]                     # fields in both the table and the target


def pair_table(ref_table, ref_ms, target_ms, ref_spw: Optional[int] = None,
               antenna_map=None, target_meta: Optional[SetMetadata] = None) -> PairedTable:
    """Read the table solved on ``ref_ms``, check it and pair its stations and fields with
    ``target_ms``'s (each set read once; ``target_meta``: the target's metadata, when the
    caller has read it)."""
    target_ms, ref_ms = str(target_ms).rstrip("/"), str(ref_ms).rstrip("/")
    ref_meta = read_metadata(ref_ms) if (Path(ref_ms) / "table.dat").is_file() else None
    table = read_solutions(ref_table, ref_ms, ref_meta)
    _check_overlap(table, target_ms)
    meta = target_meta if target_meta is not None else read_metadata(target_ms)
    windows, target_fields, ant1, ant2 = _target_windows(target_ms, meta)
    ref_stations = stations_of(ref_ms, ref_meta.antennas, "REF_MS")
    tgt_stations = stations_of(target_ms, meta.antennas, "TARGET_MS")
    ref_to_tgt = pair_antennas(ref_stations, tgt_stations, parse_antenna_map(antenna_map),
                               ant1, ant2)
    by_field = _reference_windows(table, ref_spw)
    common = [name for name in by_field if name in target_fields]
    if not common:
        raise TableMismatchError(f"no field of reference table '{table.path}' "
                                 f"({', '.join(by_field)}) is in {target_ms} ({', '.join(target_fields)})")
    return PairedTable(table, target_ms, tuple(windows), tuple(target_fields), ref_to_tgt,
                       tgt_stations.n_ant, by_field, tuple(common))


def transfer_paired(paired: PairedTable, wrap_counting: bool = True,
                    max_gap_s: float = 60.0) -> PreparedTransfer:
    """Count (or not) and transfer a paired table: one method's :class:`PreparedTransfer`."""
    if not max_gap_s > 0:
        raise TransferOptionError(f"max_gap_s must be > 0 seconds, not {max_gap_s}")
    table, fields = paired.table, list(paired.target_fields)
    unwrapped = tuple(unwrap_window(paired.by_field[name], max_gap_s, wrap_counting,
                                    table.has_rates) for name in paired.common)
    if wrap_counting:
        for u in unwrapped:
            check_interval(u, table.antenna_names, table.path)
    targets = tuple(_on_target_antennas(transfer_window(u, spw, fields.index(name), centre,
                                                        table.has_rates),
                                        paired.ref_to_tgt, paired.n_ant_target)
                    for name, u in zip(paired.common, unwrapped) for spw, centre in paired.windows)
    return PreparedTransfer(table, paired.target_ms, wrap_counting, unwrapped, targets,
                            tuple(c for _, c in paired.windows), paired.n_ant_target)


def prepare_transfer(ref_table, ref_ms, target_ms, *, wrap_counting: bool = True,
                     ref_spw: Optional[int] = None, max_gap_s: float = 60.0,
                     antenna_map=None) -> PreparedTransfer:
    """Read, check, count and transfer: :func:`transfer_table` without the writing.

    ``antenna_map``: REF=TARGET station names for stations named differently in the two
    bands (``"JC=SM"`` or a mapping; :func:`hitops.io.match.parse_antenna_map`).
    """
    if not max_gap_s > 0:
        raise TransferOptionError(f"max_gap_s must be > 0 seconds, not {max_gap_s}")
    return transfer_paired(pair_table(ref_table, ref_ms, target_ms, ref_spw, antenna_map),
                           wrap_counting, max_gap_s)


def transfer_report(prepared: PreparedTransfer, out_table: Optional[str], n_rows: int) -> TransferReport:
    """The report of a prepared transfer (``out_table`` None: no table written), logged."""
    table, unwrapped = prepared.table, prepared.unwrapped
    report = TransferReport(
        table=str(out_table) if out_table else None, reference_table=table.path, kind=table.kind,
        wrap_counting=prepared.wrap_counting,
        reference_freq_hz=tuple(u.source.ref_freq_hz for u in unwrapped),
        target_centres_hz=prepared.target_centres_hz, n_rows=n_rows,
        n_segments=int(sum(u.new_segment.sum() for u in unwrapped)),
        common_refant=tuple(_first_refant(table, u) for u in unwrapped),
        antennas=_summaries(table, unwrapped), refant_changes=_refant_changes(table, unwrapped))
    log.info("transferred %s (%s, phase at %s GHz)%s: %d reference antenna change(s)",
             table.path, table.kind, ", ".join(f"{f / 1e9:.4f}" for f in report.reference_freq_hz),
             f" to {out_table} ({n_rows} rows)" if out_table else "", len(report.refant_changes))
    for change in report.refant_changes:
        log.info("reference antenna %s -> %s at %.1f s (spectral window %d, field %d): %s",
                 change.from_antenna, change.to_antenna, change.time, change.spw, change.field,
                 "re-referred to the window's first reference antenna" if change.bridged
                 else "no antenna solved on both sides: not re-referred")
    for ant in report.antennas:
        log.info("station %s: %d solutions, %d flagged, %d wraps, largest bridged residual %.2f rad",
                 ant.name, ant.n_solutions, ant.n_flagged, ant.n_wraps, ant.max_residual_rad)
    return report


def write_target_table(prepared: PreparedTransfer, out_table, overwrite: bool = False) -> int:
    """The prepared transfer as the target-band Fringe Jones table; its number of rows."""
    from .write import write_fringe_table

    return write_fringe_table(out_table, prepared.target_ms, prepared.targets,
                              prepared.n_ant_target, overwrite)


def transfer_table(ref_table, ref_ms, target_ms, out_table, *, wrap_counting: bool = True,
                   ref_spw: Optional[int] = None, max_gap_s: float = 60.0,
                   overwrite: bool = False) -> TransferReport:
    """Transfer a reference band's fringefit/gaincal table to a target-band Fringe Jones table.

    ``ref_table`` was solved on ``ref_ms``; ``out_table`` is written for ``target_ms``
    (one row per solution, antenna and target window, the phase R_c*u at the window's
    centre, the delay u/(2*pi*nu_ref), the rate carried over).  ``wrap_counting=False``
    transfers the wrapped phases (R*phi, the CFPT analogue; for comparison only).
    ``ref_spw``: the reference window to transfer from (default: per field, the window
    with the most solutions).  ``max_gap_s``: a longer gap between solutions (or a new
    scan) restarts the rate prediction.  Nothing is written when any check fails.
    """
    prepared = prepare_transfer(ref_table, ref_ms, target_ms, wrap_counting=wrap_counting,
                                ref_spw=ref_spw, max_gap_s=max_gap_s)
    n_rows = write_target_table(prepared, out_table, overwrite)
    return transfer_report(prepared, out_table, n_rows)
