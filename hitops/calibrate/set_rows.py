"""What a step reads of a band by row number, on either backend.

The calibrator step (hitops/calibrate/phaseref) walks a band's rows by number in
chunks: the index columns of a range of rows (``index``), then data columns at some of
them (``reader``), and the transaction's staged outputs, which it reads back and
rewrites (``tx.flags_now``, ``tx.restage``); the verdict (:mod:`.verdict_sample`) reads
the TIME of every row and the rest at the rows of its blocks.  Two backends give the
same:

* :class:`MainTableRows`: a Measurement Set v2's main table (python-casacore), the row
  numbers its own; the staged columns are columns of the table;
* :class:`ProcessingSetRows`: a processing set's (field, window) groups of the run,
  numbered as the run numbers them (hitops/io/msv4/group_rows.py: a group's rows in
  time then baseline order, ROWID = its ``row_base`` + position); a staged output is
  read from the transaction's staged data group (its name one of ``tx.staging``).

The row order differs between the two (an MSv2 set interleaves fields and windows in
time; a processing set's groups follow each other), which the step does not depend on
beyond float rounding: each baseline's rows come in time order either way
(docs/msv4.md, "--calibrator-field on processing sets"); the verdict puts its rows on a
(baseline, time) grid.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Dict, Iterator, List, Sequence

import numpy as np

from ..io import tables
from ..io.msv4.group_rows import rows_by_source
from ..io.msv4.store import is_processing_set
from ..io.read import column_names
from ..io.table_rows import rows_reader


class MainTableRows:
    """A Measurement Set v2's rows through its open main table."""

    def __init__(self, table):
        self.table = table

    @property
    def n_rows(self) -> int:
        return int(self.table.nrows())

    @property
    def column_names(self) -> List[str]:
        return list(self.table.colnames())

    def index(self, columns: Sequence[str], start: int, n: int) -> Dict[str, np.ndarray]:
        """Per-row columns of rows [start, start + n)."""
        return {c: self.table.getcol(c, start, n) for c in columns}

    def reader(self, rows: np.ndarray) -> Callable[[str], np.ndarray]:
        """column -> its values at the ascending ``rows``."""
        return rows_reader(self.table, np.asarray(rows))


class ProcessingSetRows:
    """A processing set's rows of the run's groups (``sources``: PartitionSources), and
    the staged data groups of ``tx`` (a DataGroupTransaction, or None for a band the run
    only reads)."""

    def __init__(self, sources: Sequence, tx=None):
        self.sources = sorted(sources, key=lambda s: s.row_base)
        self.tx = tx

    @property
    def n_rows(self) -> int:
        return max((s.row_base + s.n_rows for s in self.sources), default=0)

    @property
    def column_names(self) -> List[str]:
        """The MSv2 names the store answers to (hitops/io/msv4/columns.py)."""
        return column_names(self.sources[0].ms) if self.sources else []

    def index(self, columns: Sequence[str], start: int, n: int) -> Dict[str, np.ndarray]:
        """Per-row columns of rows [start, start + n); a row of a group the run does not
        read (a field without partner) has TIME NaN and -1 in the others."""
        out = {c: np.full(n, np.nan) if c == "TIME" else np.full(n, -1, np.int64)
               for c in columns}
        for source in self.sources:
            lo = max(start, source.row_base)
            hi = min(start + n, source.row_base + source.n_rows)
            if lo >= hi:
                continue
            with source.open() as table:
                got = table.read_rows(list(columns), slice(lo - source.row_base,
                                                           hi - source.row_base))
            for c in columns:
                out[c][lo - start:hi - start] = got[c]
        return out

    def reader(self, rows: np.ndarray) -> Callable[[str], np.ndarray]:
        """column -> its values at the ascending ``rows`` (a staged output's name: what the
        run has written there so far)."""
        rows = np.asarray(rows, np.int64)

        def read(column: str) -> np.ndarray:
            if self.tx is not None and column in self.tx.staging.values():
                return self.tx.read_staged(rows, column)
            parts = []
            for source, _, positions in rows_by_source(self.sources, rows):
                with source.open() as table:
                    parts.append(table.read_rows([column], positions)[column])
            if not parts:
                with self.sources[0].open() as table:
                    return table.read_rows([column], np.zeros(0, np.int64))[column]
            return np.concatenate(parts) if len(parts) > 1 else parts[0]
        return read


def target_sources(run) -> list:
    """What the run reads each target group through (a processing set's PartitionSources)."""
    return [g.match.datasets["tgt"] for g in run.groups]


def reference_sources(run) -> list:
    """What the run reads each reference group through."""
    return [g.match.datasets["ref"] for g in run.groups]


@contextmanager
def open_band_rows(ms: str, columns: Sequence[str]) -> Iterator:
    """Every row of band ``ms``: a processing set's groups (their FLAG that of the data
    group of ``columns``' first data column), a Measurement Set's main table."""
    from ..io.msv4.group_rows import open_partition_groups

    sources = (open_partition_groups(ms, list(columns)).values() if is_processing_set(ms)
               else ())
    with open_set_rows(ms, sources) as rows:
        yield rows


@contextmanager
def open_set_rows(ms: str, sources: Sequence, tx=None) -> Iterator:
    """The rows of band ``ms`` as the step reads them: a processing set's through the run's
    groups ``sources`` (and ``tx``'s staged groups), a Measurement Set's main table."""
    if is_processing_set(ms):
        yield ProcessingSetRows(sources, tx)
        return
    with tables.main_table(ms) as table:
        yield MainTableRows(table)
