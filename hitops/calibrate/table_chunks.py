"""The ``--reference-table`` path's chunks: what a run is, how a chunk is read and corrected.

The pieces both of the table path's executors use: this process's loop
(hitops/calibrate/from_table.py, ``each_chunk``: chunk k+1 read on an I/O thread while
chunk k is corrected) and a cluster's workers (hitops/calibrate/table_workers.py).  A
chunk's correction and the n0 step's sums depend on that chunk alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..io.metadata import SetMetadata
from ..io.table_rows import MainTable
from ..solutions.api import PreparedTransfer
from .inputs import CalibrateOptions, Columns
from .table_source import TargetLayout, correct_chunk, window_rows
from .table_store import StoreRows

#: the main-table columns every chunk reads besides the data, the flags and the n0 column
ROW_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "FIELD_ID", "FLAG_ROW")


@dataclass(frozen=True)
class TableRun:
    """A ``--reference-table`` run, checked and planned; nothing written yet."""

    opts: CalibrateOptions
    methods: List[str]
    target_ms: str
    outputs: Dict[str, str]         # method -> column
    columns: Columns
    tgt_meta: SetMetadata           # the target's subtables, read once
    layout: TargetLayout
    n_rows: int                     # rows of the target set
    chunk_rows: int                 # rows per chunk: --chunk-rows, else from --memory-budget
    #: a processing set's groups and chunks (hitops/calibrate/table_store.py); None: MSv2
    store: Optional[StoreRows] = None

    @property
    def n_chunks(self) -> int:
        if self.store is not None:
            return self.store.n_chunks
        return -(-self.n_rows // self.chunk_rows)


@dataclass(frozen=True)
class TargetChunk:
    """Rows [start, start + n) of the target set as read: ``columns`` holds ROW_COLUMNS by
    name, ``data`` (the target column), ``flag`` (the input flags) and ``offset`` (the n0
    step's column) when it is read."""

    start: int
    columns: Dict[str, np.ndarray]

    @property
    def rows(self) -> np.ndarray:
        return np.arange(self.start, self.start + self.columns["data"].shape[0])


def read_chunk(run: TableRun, k: int, offset_column: Optional[str]) -> TargetChunk:
    """Chunk ``k`` of the target set, in storage order (python-casacore, hitops/io)."""
    names = {"data": run.columns.target_data, "flag": run.columns.flag}
    if offset_column:
        names["offset"] = offset_column
    wanted = list(dict.fromkeys(list(ROW_COLUMNS) + list(names.values())))
    if run.store is not None:   # a processing set: chunk k's rows of the group holding it
        return TargetChunk(run.store.bounds[k], _named(run.store.read(wanted, k), names))
    start = k * run.chunk_rows
    stop = min(start + run.chunk_rows, run.n_rows)
    with MainTable(run.target_ms) as table:
        read = table.read(wanted, start, stop)
    return TargetChunk(start, _named(read, names))


def _named(read: Dict[str, np.ndarray], names: Dict[str, str]) -> Dict[str, np.ndarray]:
    """The row columns by name, the data, flag and offset columns by their role."""
    cols = {name: read[name] for name in ROW_COLUMNS}
    cols.update({key: read[column] for key, column in names.items()})
    return cols


def n0_column(run: TableRun) -> Optional[str]:
    """The column the n0 step compares with (None: a point model, nothing read)."""
    columns = run.columns
    return None if columns.offset_is_model and not columns.model else columns.offset


def chunk_sums(run: TableRun, prepared: PreparedTransfer, chunk: TargetChunk) -> Dict:
    """The n0 step's per-edge sums of one chunk (n0/table.py's ``accumulate``), from zero."""
    from .n0.table import accumulate, solve_windows

    cols, layout = chunk.columns, run.layout
    offset_column = n0_column(run)
    solve_on = set(solve_windows(prepared).values())
    sums: Dict = {}
    result = correct_chunk({"pwc": prepared}, layout, cols)
    bad = cols["flag"] | cols["FLAG_ROW"][:, None, None] | result.uncalibrated[:, None, :]
    for j, _, receptors, rows in window_rows(prepared, layout, cols["DATA_DESC_ID"],
                                              cols["FIELD_ID"]):
        if j in solve_on:
            model = np.angle(cols["offset"][rows]) if offset_column else 0.0
            accumulate(sums, prepared, j, rows, cols, result.columns["pwc"][rows], ~bad[rows],
                       model, receptors)
    return sums


def merge_sums(total: Dict, part: Dict) -> None:
    """Add one chunk's sums (:func:`chunk_sums`) to the run's."""
    for key, (z, n) in part.items():
        entry = total.setdefault(key, [0j, 0])
        entry[0] = entry[0] + z
        entry[1] = entry[1] + n


@dataclass
class SampleCounts:
    """Target samples (row x channel x correlation) of the run: the report's ``samples``."""

    n_samples: int = 0
    flagged_before: int = 0
    not_calibrated: int = 0

    def add(self, before: np.ndarray, new_flag: np.ndarray) -> None:
        self.n_samples += int(before.size)
        self.flagged_before += int(before.sum())
        self.not_calibrated += int((new_flag & ~before).sum())

    def merge(self, other: "SampleCounts") -> None:
        """Add another chunk's (or worker's) counts."""
        self.n_samples += other.n_samples
        self.flagged_before += other.flagged_before
        self.not_calibrated += other.not_calibrated


@dataclass(frozen=True)
class CorrectedChunk:
    """One chunk corrected: each method's visibilities, the flags before and after."""

    outputs: Dict[str, np.ndarray]
    before: np.ndarray          # (n_row, n_chan, n_corr) the input flags and FLAG_ROW
    new_flag: np.ndarray        # before, and the samples no solution calibrates


def correct_and_flag(run: TableRun, transfers: Dict[str, PreparedTransfer],
                     chunk: TargetChunk) -> CorrectedChunk:
    """A chunk's correction by every method and its new flags."""
    cols = chunk.columns
    result = correct_chunk(transfers, run.layout, cols)
    before = cols["flag"] | cols["FLAG_ROW"][:, None, None]
    return CorrectedChunk(result.columns, before, before | result.uncalibrated[:, None, :])
