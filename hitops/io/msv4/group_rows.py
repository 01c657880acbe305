"""A processing set's (field, window) groups read as calibrate reads a Measurement Set's.

calibrate reads each band's (FIELD_ID, DATA_DESC_ID) group through one object
(hitops/io/read.py, ``open_for_reading``): positions 0..n_rows-1 in time order, a
``read(table, columns, rows)`` of a slice or of ascending positions, ``ROWID`` the
row numbers a write goes back to.  :class:`PartitionSource` is that object for a
processing set: one partition's rows of one field (a partition holds one window and
may hold several fields, one per time step), in time then baseline order, as
:class:`~hitops.io.msv4.rows.PartitionReader` gives them.  A row's ``ROWID`` is its
position plus the group's ``row_base`` (the groups of a set numbered one after the
other in key order), so a run's rows of every group are one range, as a table's are;
:meth:`PartitionSource.cells` turns positions back into (time, baseline) cells for
the writer.  Columns are named as in MSv2 and mapped by hitops/io/msv4/columns.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Dict, Optional, Sequence, Tuple

import numpy as np

from ...errors import ProcessingSetError
from ..table_rows import StorageRows
from .columns import band_group, group_of_column, is_data_column
from .layout import ProcessingSetLayout, read_layout
from .rows import PartitionReader, PartitionRows
from .store import open_store

#: grid cells per block when a partition's rows are counted
COUNT_BLOCK_CELLS = 1 << 22


@dataclass(frozen=True, eq=False)
class GroupSteps:
    """A group's rows counted per time step of its partition, from the grid alone."""

    time: np.ndarray            # (n_step,) float64: TIME (MSv2 seconds) of the group's steps
    n_rows: np.ndarray          # (n_step,) int64: rows (cells holding an integration) per step
    scan_number: np.ndarray     # (n_step,) int32: SCAN_NUMBER of each step
    interval: float             # INTERVAL of every row (the time axis' integration_time; 0: none)


@dataclass(frozen=True, eq=False)
class PartitionSource(StorageRows):
    """One (field, window) group of a processing set, read in time order (``ms``: the store)."""

    partition: str = ""
    key: Tuple[int, int] = (0, 0)            # (FIELD_ID, DATA_DESC_ID)
    steps: np.ndarray = field(default=None)  # the partition's time steps of this field
    step_start: np.ndarray = field(default=None)   # (n_steps + 1,) first position per step
    row_base: int = 0                        # ROWID of position 0
    several_fields: bool = False             # the partition holds other fields' steps too
    readers: Dict[str, PartitionReader] = field(default=None)   # data group -> reader
    group: str = "base"                      # the band's data group (FLAG, WEIGHT: its own)
    positions_are_rows: ClassVar[bool] = False   # ROWID = row_base + position

    def open(self) -> "PartitionTable":
        return PartitionTable(self)

    def reader(self, group: str) -> PartitionReader:
        """The partition's reader of data group ``group`` (made on first use)."""
        if group not in self.readers:
            first = next(iter(self.readers.values()))
            self.readers[group] = PartitionReader(first.layout, self.partition, group)
        return self.readers[group]

    def cell_shape(self, column: str) -> Tuple[int, ...]:
        group = group_of_column(column) if is_data_column(column) else self.group
        role = "DATA" if is_data_column(column) else column
        return self.reader(group).cell_shape(role)

    def read(self, table, columns: Sequence[str], rows) -> Dict[str, np.ndarray]:
        return table.read_rows(list(columns), rows)

    def time_steps(self) -> GroupSteps:
        """The group's time steps, rows per step and scans, as counted when it was opened:
        what a pass over its TIME, SCAN_NUMBER and INTERVAL columns would find, unread."""
        reader = self.reader(self.group)
        return GroupSteps(time=reader.times[self.steps], n_rows=np.diff(self.step_start),
                          scan_number=reader.scan_numbers[self.steps],
                          interval=reader.integration_time)

    def antennas(self, start: int, stop: int) -> Tuple[np.ndarray, np.ndarray]:
        """(ANTENNA1, ANTENNA2) of positions [start, stop): from the baselines of their
        cells, so only a partly filled step's presence is read."""
        ant1, ant2 = self.reader(self.group).baseline_antennas
        full = self._full_steps(start, stop - 1) if stop > start else None
        if full is not None:
            # every cell of these steps a row: the baselines' antennas repeated per step,
            # no position divided into its step and baseline
            s0, s1 = full
            pick = slice(start - int(self.step_start[s0]), stop - int(self.step_start[s0]))
            return np.tile(ant1, s1 - s0)[pick], np.tile(ant2, s1 - s0)[pick]
        _, baseline = self.cells(np.arange(start, stop, dtype=np.int64))
        return ant1[baseline], ant2[baseline]

    def _full_steps(self, first: int, last: int) -> Optional[Tuple[int, int]]:
        """[s0, s1): the group's steps that positions ``first``..``last`` fall in, when every
        cell of them is a row; None when some cell of them is not."""
        s0 = int(np.searchsorted(self.step_start, first, side="right")) - 1
        s1 = int(np.searchsorted(self.step_start, last, side="right"))
        n_baseline = self.reader(self.group).n_baseline
        return (s0, s1) if np.all(np.diff(self.step_start[s0:s1 + 1]) == n_baseline) else None

    def cells(self, positions: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(time index in the partition, baseline_id) of each position (ascending or not)."""
        positions = np.asarray(positions, np.int64)
        reader = self.reader(self.group)
        # the steps these positions fall in; when every cell of them is a row, a
        # position's step and baseline follow by division (no search per position)
        full = (self._full_steps(int(positions.min()), int(positions.max()))
                if positions.size else None)
        if full is not None:
            offset = positions - self.step_start[full[0]]
            return (self.steps[full[0] + offset // reader.n_baseline],
                    offset % reader.n_baseline)
        step = np.searchsorted(self.step_start, positions, side="right") - 1
        times = self.steps[step]
        rank = positions - self.step_start[step]        # the k-th row of its time step
        per_step = np.diff(self.step_start)[step]
        if positions.size == 0 or np.all(per_step == reader.n_baseline):
            return times, rank     # every cell of these steps a row: the rank is the baseline
        t_a, t_b = int(times.min()), int(times.max()) + 1
        present = reader.present(t_a, t_b)
        # baseline of the k-th present cell of each time step
        order = np.cumsum(present, axis=1) - 1
        t_rel, bl = np.nonzero(present)
        lookup = np.full(present.shape, -1, np.int64)
        lookup[t_rel, order[t_rel, bl]] = bl
        return times, lookup[times - t_a, rank]


def rows_by_source(sources: Sequence[PartitionSource], rows: np.ndarray):
    """(source, the indices of ``rows`` in it, their positions) for each of ``sources``
    (sorted by ``row_base``) that holds some of the ascending ROWIDs ``rows``."""
    rows = np.asarray(rows, np.int64)
    bases = np.array([s.row_base for s in sources], np.int64)
    which = np.searchsorted(bases, rows, side="right") - 1
    if which.size and which[0] < 0:
        raise ProcessingSetError(f"row {int(rows[0])} lies in no group of the run; this is a "
                                 "hitops bug")
    bounds = np.searchsorted(which, np.arange(len(sources) + 1))
    for k, source in enumerate(sources):
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        if lo == hi:
            continue
        positions = rows[lo:hi] - source.row_base
        if positions[-1] >= source.n_rows:
            raise ProcessingSetError(f"'{source.ms}': row {int(rows[hi - 1])} lies in no group "
                                     "of the run; this is a hitops bug")
        yield source, np.arange(lo, hi), positions


class PartitionTable:
    """What :class:`PartitionSource` reads through: the counterpart of
    :class:`hitops.io.table_rows.MainTable` (``n_rows``, ``read``, ``read_rows``)."""

    def __init__(self, source: PartitionSource):
        self.source = source

    @property
    def n_rows(self) -> int:
        return self.source.n_rows

    def read(self, columns: Sequence[str], start: int, stop: int) -> Dict[str, np.ndarray]:
        return self.read_rows(columns, slice(int(start), int(stop)))

    def read_rows(self, columns: Sequence[str], rows) -> Dict[str, np.ndarray]:
        """``columns`` at positions ``rows`` (a slice, ascending positions, or None)."""
        src = self.source
        if rows is None or isinstance(rows, slice):
            a, b, _ = (rows or slice(None)).indices(src.n_rows)
            positions = np.arange(a, max(a, b), dtype=np.int64)
        else:
            positions = np.asarray(rows, np.int64)
        if positions.size == 0:
            return _empty(src, columns)
        s0 = int(np.searchsorted(src.step_start, positions.min(), side="right")) - 1
        s1 = int(np.searchsorted(src.step_start, positions.max(), side="right"))
        span = (int(src.steps[s0]), int(src.steps[s1 - 1]) + 1)
        n_expected = int(src.step_start[s1] - src.step_start[s0])
        # ascending distinct positions as many as the steps' rows: all of them, no gather
        pick = slice(None) if positions.size == n_expected else positions - src.step_start[s0]
        roles = [c for c in ("FLAG", "UVW") if c in columns]
        if {"WEIGHT", "SIGMA"} & set(columns):
            roles.append("WEIGHT")
        band = [c for c in columns if is_data_column(c) and group_of_column(c) == src.group]
        rows_read = _rows(src, src.group, span, (["DATA"] if band else []) + roles, n_expected)
        out = _row_columns(src, rows_read, columns, pick, positions)
        for c in band:
            out[c] = rows_read.data[pick]
        for role in ("FLAG", "UVW"):
            if role in columns:
                out[role] = getattr(rows_read, role.lower())[pick]
        if {"WEIGHT", "SIGMA"} & set(columns):
            weight = rows_read.weight[pick].mean(axis=1, dtype=np.float64).astype(np.float32)
            if "WEIGHT" in columns:
                out["WEIGHT"] = weight
            if "SIGMA" in columns:
                with np.errstate(divide="ignore"):
                    out["SIGMA"] = np.where(weight > 0, 1 / np.sqrt(weight), np.inf
                                            ).astype(np.float32)
        for c in columns:
            if is_data_column(c) and c not in out:   # a column of another data group
                out[c] = _rows(src, group_of_column(c), span, ["DATA"], n_expected).data[pick]
        return out

    def close(self) -> None:
        pass

    def __enter__(self) -> "PartitionTable":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _rows(src: PartitionSource, group: str, span, roles, n_expected: int) -> PartitionRows:
    """The partition's rows of the time steps ``span`` of this group's field."""
    reader = src.reader(group)
    # steps whose rows (counted when the group was opened) fill every baseline: their
    # presence is not read again
    every_cell = not src.several_fields and bool(np.all(
        np.diff(src.step_start[np.searchsorted(src.steps, span[0]):
                               np.searchsorted(src.steps, span[1]) + 1]) == reader.n_baseline))
    rows = reader.read(span, roles, every_cell=every_cell)
    if src.several_fields:
        keep = rows.field_id == src.key[0]
        rows = PartitionRows(**{k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] ==
                                    keep.shape else v) for k, v in vars(rows).items()})
    if rows.n_row != n_expected:
        raise ProcessingSetError(
            f"'{src.ms}' partition '{src.partition}': time steps {span[0]}-{span[1] - 1} hold "
            f"{rows.n_row} rows where the run's index found {n_expected}; the store changed "
            "during the run: run again on a store nothing else writes")
    return rows


def _row_columns(src: PartitionSource, rows: PartitionRows, columns, pick,
                 positions) -> Dict:
    """The per-row columns asked for, at ``pick`` of ``rows`` (the group's ``positions``)."""
    reader = src.reader(src.group)
    n = positions.size
    values = {"TIME": lambda: rows.time[pick], "ANTENNA1": lambda: rows.antenna1[pick],
              "ANTENNA2": lambda: rows.antenna2[pick],
              "SCAN_NUMBER": lambda: rows.scan_number[pick],
              "FIELD_ID": lambda: rows.field_id[pick],
              "DATA_DESC_ID": lambda: rows.data_desc_id[pick],
              "INTERVAL": lambda: np.full(n, reader.integration_time),
              "FLAG_ROW": lambda: np.zeros(n, bool),
              "ROWID": lambda: src.row_base + positions}
    return {c: values[c]() for c in columns if c in values}


def _empty(src: PartitionSource, columns) -> Dict[str, np.ndarray]:
    """No row: every column with its cell shape, as a table's reader gives it."""
    out = {}
    for c in columns:
        if c in ("TIME", "INTERVAL"):
            out[c] = np.zeros(0, np.float64)
        elif c == "FLAG_ROW":
            out[c] = np.zeros(0, bool)
        elif c in ("WEIGHT", "SIGMA"):
            out[c] = np.zeros((0,) + src.cell_shape("FLAG")[1:], np.float32)
        elif c == "UVW":
            out[c] = np.zeros((0, 3), np.float64)
        elif c == "FLAG":
            out[c] = np.zeros((0,) + src.cell_shape("FLAG"), bool)
        elif is_data_column(c):
            out[c] = np.zeros((0,) + src.cell_shape(c), np.complex64)
        else:
            out[c] = np.zeros(0, np.int64 if c == "ROWID" else np.int32)
    return out


def _step_rows(reader: PartitionReader) -> np.ndarray:
    """(n_time,) int64 rows of each time step, counted in blocks of the presence grid."""
    step = max(1, COUNT_BLOCK_CELLS // max(1, reader.n_baseline))
    return np.concatenate([reader.present(t, min(t + step, reader.n_time)).sum(axis=1)
                           for t in range(0, reader.n_time, step)] or [np.zeros(0, np.int64)]
                          ).astype(np.int64)


def open_partition_groups(ps: str, columns: Sequence[str],
                          layout: ProcessingSetLayout = None) -> Dict[tuple, PartitionSource]:
    """One :class:`PartitionSource` per (FIELD_ID, DATA_DESC_ID) group of processing set ``ps``,
    reading the data group of the band's data column (:func:`columns.band_group`)."""
    layout = layout or read_layout(open_store(ps))
    group = band_group(columns)
    found = []
    for place in sorted(layout.partitions, key=lambda p: p.name):
        reader = PartitionReader(layout, place.name, group)
        per_step = _step_rows(reader)
        fields = reader.field_ids
        distinct = np.unique(fields)
        for field_id in distinct:
            steps = np.flatnonzero(fields == field_id).astype(np.int64)
            start = np.concatenate([[0], np.cumsum(per_step[steps])]).astype(np.int64)
            found.append(((int(field_id), place.data_desc_id), place.name, steps, start,
                          distinct.size > 1, reader))
    out, base = {}, 0
    for key, name, steps, start, several, reader in sorted(found, key=lambda f: f[0]):
        if key in out:
            raise ProcessingSetError(
                f"'{ps}': partitions '{out[key].partition}' and '{name}' both hold field "
                f"{layout.fields.names[key[0]]} in data description {key[1]}; hitops pairs one "
                "partition per field and window: convert the set again with xradio's default "
                "partition scheme")
        out[key] = PartitionSource(ms=ps, n_rows=int(start[-1]), partition=name, key=key,
                                   steps=steps, step_start=start, row_base=base,
                                   several_fields=several, readers={group: reader}, group=group)
        base += int(start[-1])
    return out


def row_count(ps: str) -> int:
    """Rows of every partition of ``ps`` (cells holding an integration): the presence
    arrays counted, no field or scan read."""
    layout = read_layout(open_store(ps))
    return sum(int(_step_rows(PartitionReader(layout, place.name)).sum())
               for place in layout.partitions)


def weight_source(ps: str, sample_rows: int) -> str:
    """'weight' when the processing set's WEIGHT holds informative values (finite, positive,
    not all 1) in the first ``sample_rows`` rows of each group, else 'data': what
    hitops/tracking/options.py's ``sigma_source`` says of a Measurement Set (MSv4 keeps no
    sigma; SIGMA is 1/sqrt(WEIGHT) here, so 'weight' says the same)."""
    from .columns import column_names

    if "WEIGHT" not in column_names(open_store(ps)):
        return "data"
    informative = False
    for source in open_partition_groups(ps, ["DATA"]).values():
        with source.open() as table:
            weight = table.read(["WEIGHT"], 0, min(source.n_rows, sample_rows))["WEIGHT"]
        if weight.size and not (np.all(np.isfinite(weight)) and np.all(weight > 0)):
            return "data"
        informative |= bool(weight.size) and not np.all(weight == 1.0)
    return "weight" if informative else "data"
