"""The calibrator step's passes over the target set, chunk by chunk, inside the memory budget.

The set is read in chunks of the run's rows per chunk (``run.chunk_rows``, from
``--chunk-rows`` or ``--memory-budget``: hitops/calibrate/memory.py): per chunk the index
columns (TIME, ANTENNA1, ANTENNA2, FIELD_ID, DATA_DESC_ID, SCAN_NUMBER) of its rows, then
the staged column of the rows of one target window only.  Between chunks only sums per
tracking scan are kept (n_ant^2 baselines x channels x hands each), and of each scan's
TIME its runs of equal values (one per integration in a set in time order), from which
its mean is taken as one read of the scan's rows would take it.

Sums added chunk after chunk equal, bit for bit, one sum over all the rows
(kernels/phase_ref.add_baseline_sums adds row after row); the target's sums of what is
left keep the blocks of ``chunk_rows`` target rows in which the step always summed them
(:class:`TargetLeft`), so a run's output does not depend on how its chunks fall.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Tuple

import numpy as np

from ...kernels.phase_ref import add_baseline_sums
from .bridge import tracking_scans

#: the index columns read per chunk
INDEX_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "FIELD_ID", "SCAN_NUMBER")


@dataclass(frozen=True)
class RowsOf:
    """Some rows of one chunk (ascending) and their index columns."""

    rows: np.ndarray             # absolute row numbers
    time: np.ndarray
    ant1: np.ndarray             # int64
    ant2: np.ndarray
    field: np.ndarray
    scan_number: np.ndarray
    scan: np.ndarray             # the transfer's tracking scan (bridge.tracking_scans)

    def code(self, n_ant: int) -> np.ndarray:
        """Each row's baseline as ant1 * n_ant + ant2."""
        return self.ant1 * n_ant + self.ant2

    def pick(self, mask: np.ndarray) -> "RowsOf":
        return RowsOf(self.rows[mask], self.time[mask], self.ant1[mask], self.ant2[mask],
                      self.field[mask], self.scan_number[mask], self.scan[mask])


@dataclass(frozen=True)
class WindowChunk:
    """One chunk's rows of one target window that this run wrote."""

    cal: RowsOf
    target: RowsOf


@dataclass(frozen=True)
class WindowPass:
    """A pass over one target window: which rows belong to it, and how to read them."""

    ddid: int
    cal_field: int
    target_fields: Tuple[int, ...]
    groups: List
    chunk_rows: int

    def chunks(self, set_rows, written: np.ndarray) -> Iterator[WindowChunk]:
        """The window's rows chunk by chunk (chunks without any are skipped); ``set_rows``
        the target's (:mod:`hitops.calibrate.set_rows`)."""
        n_rows = set_rows.n_rows
        for start in range(0, n_rows, self.chunk_rows):
            n = min(self.chunk_rows, n_rows - start)
            index = set_rows.index(INDEX_COLUMNS + ("DATA_DESC_ID",), start, n)
            here = written[start:start + n] & (index["DATA_DESC_ID"] == self.ddid)
            if not here.any():
                continue
            cols = {c: index[c][here] for c in INDEX_COLUMNS}
            rows = RowsOf(start + np.flatnonzero(here), cols["TIME"],
                          cols["ANTENNA1"].astype(np.int64), cols["ANTENNA2"].astype(np.int64),
                          cols["FIELD_ID"], cols["SCAN_NUMBER"],
                          tracking_scans(self.groups, cols["TIME"], cols["FIELD_ID"]))
            yield WindowChunk(rows.pick(rows.field == self.cal_field),
                              rows.pick(np.isin(rows.field, self.target_fields)))


@dataclass
class ScanRuns:
    """Each tracking scan's TIME as runs of equal values, in row order: its mean is the
    mean of all its rows' TIME (np.mean of the same array, so the same number)."""

    values: Dict[int, List[float]] = field(default_factory=dict)
    lengths: Dict[int, List[int]] = field(default_factory=dict)

    def add(self, scan: int, time: np.ndarray) -> None:
        values, lengths = self.values.setdefault(scan, []), self.lengths.setdefault(scan, [])
        starts = np.flatnonzero(np.concatenate([[True], time[1:] != time[:-1]]))
        for i, run_length in zip(starts, np.diff(np.append(starts, time.size))):
            if values and values[-1] == time[i]:
                lengths[-1] += int(run_length)
            else:
                values.append(float(time[i]))
                lengths.append(int(run_length))

    def mean(self, scan: int) -> float:
        return float(np.mean(np.repeat(np.array(self.values[scan]), self.lengths[scan])))


@dataclass
class ScanSums:
    """Per tracking scan, sums and counts of unflagged samples per baseline code
    (ant1 * n_ant + ant2), channel and hand, added chunk after chunk."""

    shape: Tuple[int, int, int]          # (n_ant^2, n_chan, n_hand)
    sums: Dict[int, np.ndarray] = field(default_factory=dict)
    counts: Dict[int, np.ndarray] = field(default_factory=dict)

    def add(self, scan: int, vis, flag, code, hand_corr) -> None:
        if scan not in self.sums:
            self.sums[scan] = np.zeros(self.shape, np.complex128)
            self.counts[scan] = np.zeros(self.shape, np.int64)
        self.sums[scan], self.counts[scan] = add_baseline_sums(
            self.sums[scan], self.counts[scan], vis, flag, code, hand_corr)

    def scans(self) -> np.ndarray:
        return np.array(sorted(self.sums), np.int64)


@dataclass(frozen=True)
class CalibratorScans:
    """What the calibrator pass keeps: per tracking scan (ascending) its mean time, first
    SCAN_NUMBER and sums over the baselines seen (``baselines``: ascending codes)."""

    scans: np.ndarray
    times: np.ndarray
    scan_numbers: List[int]
    baselines: np.ndarray        # (n_bl,) ant1 * n_ant + ant2 of every calibrator baseline
    sums: np.ndarray             # (n_scan, n_bl, n_chan, n_hand) complex128
    counts: np.ndarray

    def ant1(self, n_ant: int) -> np.ndarray:
        return self.baselines // n_ant

    def ant2(self, n_ant: int) -> np.ndarray:
        return self.baselines % n_ant


def calibrator_pass(set_rows, tx, column: str, window: WindowPass, hand_corr: np.ndarray,
                    model_column: Optional[str], n_ant: int, n_chan: int) -> CalibratorScans:
    """The staged column on the calibrator's rows, model divided, summed per tracking scan
    and baseline, chunk by chunk."""
    from .solve import model_divided

    sums = ScanSums((n_ant * n_ant, n_chan, hand_corr.size))
    runs, first_number, seen = ScanRuns(), {}, np.zeros(n_ant * n_ant, bool)
    for chunk in window.chunks(set_rows, tx.rows_written):
        cal = chunk.cal
        if not cal.rows.size:
            continue
        read = set_rows.reader(cal.rows)
        vis = model_divided(read(column), read(model_column) if model_column else None)
        flags, code = tx.flags_now(set_rows, cal.rows), cal.code(n_ant)
        seen[code] = True
        for scan in np.unique(cal.scan):
            mine = cal.scan == scan
            sums.add(int(scan), vis[mine], flags[mine], code[mine], hand_corr)
            runs.add(int(scan), cal.time[mine])
            first_number.setdefault(int(scan), int(cal.scan_number[mine][0]))
    scans = sums.scans()
    baselines = np.flatnonzero(seen).astype(np.int64)
    return CalibratorScans(
        scans, np.array([runs.mean(s) for s in scans]), [first_number[s] for s in scans],
        baselines, np.stack([sums.sums[s][baselines] for s in scans]),
        np.stack([sums.counts[s][baselines] for s in scans]))


@dataclass
class TargetLeft:
    """What the calibrator's terms leave on the target, summed per tracking scan and
    baseline code, in blocks of ``block`` target rows (a block's own sum first, then added
    to the total: the step's order since it first ran, kept so the output does not move)."""

    block: int
    shape: Tuple[int, int, int]
    total: ScanSums = field(init=False)      # the blocks closed so far
    partial: ScanSums = field(init=False)    # the open block's own sums
    in_block: int = 0                        # target rows in the open block
    runs: ScanRuns = field(default_factory=ScanRuns)
    n_rows: int = 0

    def __post_init__(self):
        self.total, self.partial = ScanSums(self.shape), ScanSums(self.shape)

    def add(self, rows: RowsOf, vis, flags, hand_corr, n_ant: int) -> None:
        start = 0
        while start < rows.rows.size:
            stop = min(rows.rows.size, start + self.block - self.in_block)
            part = slice(start, stop)
            code, scan = rows.code(n_ant)[part], rows.scan[part]
            for s in np.unique(scan):
                mine = scan == s
                self.partial.add(int(s), vis[part][mine], flags[part][mine], code[mine],
                                 hand_corr)
            self.in_block += stop - start
            if self.in_block == self.block:
                self._close_block()
            start = stop
        for s in np.unique(rows.scan):
            self.runs.add(int(s), rows.time[rows.scan == s])
        self.n_rows += rows.rows.size

    def _close_block(self) -> None:
        for s in self.partial.sums:
            if s not in self.total.sums:
                self.total.sums[s] = np.zeros(self.shape, np.complex128)
                self.total.counts[s] = np.zeros(self.shape, np.int64)
            self.total.sums[s] = self.total.sums[s] + self.partial.sums[s]
            self.total.counts[s] = self.total.counts[s] + self.partial.counts[s]
        self.partial, self.in_block = ScanSums(self.shape), 0

    def finish(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(scans, mean times, sums (n_scan * n_ant^2, n_chan, n_hand), counts), indexed
        scan * n_ant^2 + code as :func:`.apply.target_integers` takes them."""
        self._close_block()
        scans = self.total.scans()
        return (scans, np.array([self.runs.mean(s) for s in scans]),
                np.concatenate([self.total.sums[s] for s in scans]),
                np.concatenate([self.total.counts[s] for s in scans]))
