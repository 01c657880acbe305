"""Rows of a Measurement Set laid out on a (baseline, time) grid.

FPT and coherence metrics work on per-baseline phase series in time order,
whatever order the rows are stored in.  :func:`baseline_time_layout` maps
every row to its (baseline, time) cell and gives the inverse lookup, with -1
for cells that have no row; a duplicate (TIME, ANTENNA1, ANTENNA2) raises,
since such data (several fields, spectral windows or sub-arrays mixed in one
table) must be partitioned first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MeasurementSetError


class GridShape:
    """n_bl and n_time of a (baseline, time) grid with ``ant1`` (n_bl,) and ``times``
    (n_time,) arrays (the layout here, calibrate's match and the trackers' grid)."""

    @property
    def n_bl(self) -> int:
        return self.ant1.size

    @property
    def n_time(self) -> int:
        return self.times.size


@dataclass(frozen=True)
class BaselineTimeLayout(GridShape):
    ant1: np.ndarray        # (n_bl,) ANTENNA1 of each baseline
    ant2: np.ndarray        # (n_bl,) ANTENNA2 of each baseline
    times: np.ndarray       # (n_time,) distinct times, ascending
    bl_of_row: np.ndarray   # (n_row,) baseline index of each row
    time_of_row: np.ndarray  # (n_row,) time index of each row
    rows: np.ndarray        # (n_bl, n_time) row index, -1 where the cell is empty

    def to_grid(self, values: np.ndarray, fill) -> np.ndarray:
        """Scatter per-row ``values`` (n_row, ...) onto (n_bl, n_time, ...)."""
        grid = np.full((self.n_bl, self.n_time) + values.shape[1:], fill, dtype=values.dtype)
        grid[self.bl_of_row, self.time_of_row] = values
        return grid

    def from_grid(self, grid: np.ndarray) -> np.ndarray:
        """Gather (n_bl, n_time, ...) back to per-row order (n_row, ...)."""
        return grid[self.bl_of_row, self.time_of_row]


def unique_times(time: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Distinct times (merging those closer than ``tolerance``) and each row's index."""
    order = np.argsort(time, kind="stable")
    sorted_t = time[order]
    new_group = np.empty(sorted_t.size, dtype=bool)
    new_group[:1] = True
    new_group[1:] = np.diff(sorted_t) > tolerance
    group = np.cumsum(new_group) - 1
    times = sorted_t[new_group]
    time_of_row = np.empty_like(group)
    time_of_row[order] = group
    return times, time_of_row


def baseline_time_layout(time: np.ndarray, ant1: np.ndarray, ant2: np.ndarray,
                         tolerance: float = 0.0, source: str = "Measurement Set"
                         ) -> BaselineTimeLayout:
    """Lay rows out by (baseline, time).

    ``tolerance`` (seconds) merges timestamps that differ by rounding only.
    ``source`` names the data in error messages.
    """
    time = np.asarray(time, dtype=np.float64)
    ant1 = np.asarray(ant1, dtype=np.int64)
    ant2 = np.asarray(ant2, dtype=np.int64)
    n_ant = int(max(ant1.max(initial=-1), ant2.max(initial=-1))) + 1
    pair_key = ant1 * max(n_ant, 1) + ant2
    pairs, bl_of_row = np.unique(pair_key, return_inverse=True)
    times, time_of_row = unique_times(time, tolerance)
    rows = np.full((pairs.size, times.size), -1, dtype=np.int64)
    rows[bl_of_row, time_of_row] = np.arange(time.size)
    filled = np.count_nonzero(rows >= 0)
    if filled != time.size:
        cell = bl_of_row * times.size + time_of_row
        counts = np.bincount(cell, minlength=rows.size)
        dup = int(np.argmax(counts))
        b, t = divmod(dup, times.size)
        raise MeasurementSetError(
            f"{source}: {time.size - filled} rows share (TIME, ANTENNA1, ANTENNA2) with "
            f"another row, e.g. antennas {pairs[b] // max(n_ant, 1)}-{pairs[b] % max(n_ant, 1)} "
            f"at TIME {times[t]:.3f}; the data mix several fields, spectral windows or "
            "sub-arrays: split them (e.g. CASA split by field/spw) and run on each part")
    return BaselineTimeLayout(
        ant1=(pairs // max(n_ant, 1)).astype(np.int32),
        ant2=(pairs % max(n_ant, 1)).astype(np.int32),
        times=times, bl_of_row=bl_of_row, time_of_row=time_of_row, rows=rows)
