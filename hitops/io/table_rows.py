"""Row ranges and row sets of a main table read with python-casacore, no dask graph.

:class:`MainTable` holds one table open and reads exactly the columns asked for
(``getcol(column, startrow, nrow)``: no query, the cheapest public path);
:func:`rows_reader` reads a set of rows as few getcol calls as it can;
:class:`StorageRows` stands for a whole table read this way in place of a dask-ms
dataset (hitops/io/read.py; its subclass in hitops/io/time_sorted.py reads a table
stored out of time order in time order).  python-casacore holds the GIL in every
call, so reads on one thread and writes on another never run inside casacore at
the same time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Dict, Sequence

import numpy as np

from . import tables


class MainTable:
    """One main table held open to read row ranges of columns in storage order.

    python-casacore's ``getcol(column, startrow, nrow)``: exactly the columns asked
    for, no dask graph, no query (the cheapest public path; calibrate's index pass of
    a table read in storage order).  A context manager: the table closes on exit.
    """

    def __init__(self, ms: str):
        self.ms = ms
        self._table = tables.main_table(ms)

    @property
    def n_rows(self) -> int:
        return int(self._table.nrows())

    def read(self, columns: Sequence[str], start: int, stop: int) -> Dict[str, np.ndarray]:
        """Rows [start, stop) of ``columns``."""
        return {c: self._table.getcol(c, int(start), int(stop - start)) for c in columns}

    def read_rows(self, columns: Sequence[str], rows) -> Dict[str, np.ndarray]:
        """``columns`` at ``rows`` (a slice, ascending row numbers, or None for all);
        ``ROWID`` gives the row numbers themselves."""
        if rows is None or isinstance(rows, slice):
            start, stop, _ = (rows or slice(None)).indices(self.n_rows)
            out = self.read([c for c in columns if c != "ROWID"], start, stop)
            row_ids = np.arange(start, stop, dtype=np.int64)
        else:
            row_ids = np.asarray(rows, dtype=np.int64)
            read = rows_reader(self._table, row_ids)
            out = {c: read(c) for c in columns if c != "ROWID"}
        if "ROWID" in columns:
            out["ROWID"] = row_ids
        return out

    def close(self) -> None:
        self._table.close()

    def __enter__(self) -> "MainTable":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: rows_reader reads runs of consecutive rows one getcol each when there are at most this
#: many runs, else through one row selection
MAX_RUNS = 512


def rows_reader(table, rows: np.ndarray):
    """A function column -> values at ascending ``rows`` of an open casacore ``table``:
    one getcol per run of consecutive rows when the runs are few (a table in time order),
    else one getcol through a row selection (``selectrows``)."""
    if rows.size == table.nrows():
        return table.getcol
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    if breaks.size < MAX_RUNS:
        starts = np.concatenate([[0], breaks])
        stops = np.concatenate([breaks, [rows.size]])

        def read_runs(column):
            parts = [table.getcol(column, int(rows[a]), int(b - a)) for a, b in zip(starts, stops)]
            return np.concatenate(parts) if len(parts) > 1 else parts[0]
        return read_runs
    return table.selectrows(rows).getcol


@dataclass(frozen=True)
class StorageRows:
    """A whole main table read with python-casacore in place of a dask-ms dataset
    (:func:`hitops.io.read.open_for_reading`; :func:`hitops.io.read.compute_columns`
    reads it): positions are row numbers (a table read in storage order).  Writes
    to a table read this way need no dask-ms either (no dask-ms handle is open)."""

    ms: str
    n_rows: int
    #: ROWID is the position (a table's row number); False for a processing set's group
    positions_are_rows: ClassVar[bool] = True

    @property
    def sizes(self) -> Dict[str, int]:
        return {"row": self.n_rows}

    def read(self, table: MainTable, columns: Sequence[str], rows) -> Dict[str, np.ndarray]:
        """Positions ``rows`` (a slice, ascending positions or None) of ``columns`` from the
        open ``table``; ``ROWID`` gives the row numbers."""
        return table.read_rows(list(columns), rows)

    def open(self) -> MainTable:
        """What :meth:`read` reads through, held open (a processing set's groups give their own:
        hitops/io/msv4/group_rows.py)."""
        return MainTable(self.ms)

    def cell_shape(self, column: str) -> tuple:
        """The shape of one row's cell of ``column`` (DATA: (n_chan, n_corr))."""
        with tables.main_table(self.ms) as t:
            return tuple(t.getcell(column, 0).shape)
