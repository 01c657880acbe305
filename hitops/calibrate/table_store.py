"""The ``--reference-table`` path's target rows when the target is an MSv4 processing set.

The table path (hitops/calibrate/from_table.py) corrects the target row by row in chunks
of rows in storage order.  A processing set's rows are its groups' (hitops/io/msv4/
group_rows.py: each partition's rows of one field in time then baseline order, ROWID =
the group's first row + position), so :class:`StoreRows` reads chunk k through the one
group that holds it.  Its chunks end at a group's end or at a time step's: a data
group's write covers whole time steps (hitops/io/msv4/data_group.py), so a chunk ending
inside a step would have the next chunk's write blank that step's first cells.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Sequence, Tuple

import numpy as np

from ..io.msv4.group_rows import PartitionSource, open_partition_groups


@dataclass(frozen=True)
class StoreRows:
    """A processing set's groups in row order and the row bounds of each chunk."""

    sources: Tuple[PartitionSource, ...]
    bounds: Tuple[int, ...]             # chunk k holds rows [bounds[k], bounds[k + 1])

    @classmethod
    def of(cls, ps: str, columns: Sequence[str], chunk_rows: int) -> "StoreRows":
        """The groups of ``ps`` read for ``columns`` (the band's data group), in chunks of at
        most ``chunk_rows`` rows (at least one time step each)."""
        sources = tuple(sorted(open_partition_groups(ps, columns).values(),
                               key=lambda s: s.row_base))
        bounds = [0]
        for source in sources:
            starts = source.row_base + np.asarray(source.step_start, np.int64)
            while bounds[-1] < starts[-1]:
                # the last step start within chunk_rows of this chunk's start, past it
                stop = int(starts[np.searchsorted(starts, bounds[-1] + chunk_rows, "right") - 1])
                if stop <= bounds[-1]:   # one step longer than chunk_rows: that step alone
                    stop = int(starts[np.searchsorted(starts, bounds[-1], "right")])
                bounds.append(stop)
        return cls(sources, tuple(bounds))

    @property
    def n_chunks(self) -> int:
        return len(self.bounds) - 1

    def read(self, columns: Sequence[str], k: int) -> Dict[str, np.ndarray]:
        """``columns`` (MSv2 names, hitops/io/msv4/columns.py) of chunk ``k``'s rows."""
        start, stop = self.bounds[k], self.bounds[k + 1]
        source = self._source_of(start)
        with source.open() as table:
            return table.read(list(columns), start - source.row_base, stop - source.row_base)

    def step_span(self, k: int) -> Tuple[str, int, int]:
        """(partition, first time step, last time step) that chunk ``k``'s rows lie in."""
        start, stop = self.bounds[k], self.bounds[k + 1]
        source = self._source_of(start)
        first, last = np.searchsorted(source.step_start, [start - source.row_base,
                                                          stop - 1 - source.row_base], "right") - 1
        return source.partition, int(source.steps[first]), int(source.steps[last])

    def _source_of(self, row: int) -> PartitionSource:
        return next(s for s in self.sources if s.row_base <= row < s.row_base + s.n_rows)
