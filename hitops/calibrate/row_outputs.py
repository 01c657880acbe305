"""A chunk's transfer results, from the baseline batches' (baseline, time) cells to target rows.

Each group's :class:`~hitops.calibrate.transfer.TransferResult` holds its output on
the group's cells; :func:`rows_of_batches` puts every group's output in the chunk's
target row order (:class:`RowOutputs`), which is what the write stages.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from .transfer import TransferResult


@dataclass
class RowOutputs:
    """One chunk's transfer in the target rows' order."""

    phasor_rows: Dict[int, np.ndarray]            # method code -> (n_row, n_corr) complex64
    calibrated: np.ndarray                        # (n_row, n_corr) bool
    # a per-channel transfer's delay across the target window, seconds (channels.py)
    delay_rows: Optional[Dict[int, np.ndarray]] = None


@dataclass
class PlacedGroup:
    """Where a baseline batch's output goes: its baselines and, for a compact copy sent to
    a remote worker, the chunk rows it holds and its own row grid (None: threads, the
    group's cells hold chunk rows)."""

    bls: np.ndarray
    picked: Optional[np.ndarray]
    local_grid: Optional[np.ndarray]


def rows_of_batches(tgt_grid: np.ndarray, n_rows: int, n_corr: int, codes: List[int],
                   placed: List[PlacedGroup], results: List[TransferResult]) -> RowOutputs:
    """Each method's phasors (and delays), the calibrated mask, in the chunk's row order.

    ``tgt_grid`` (n_bl, n_time): the chunk's target row of each cell, or -1; ``codes``:
    the run's method codes; ``placed`` and ``results``: the groups, in baseline order.
    """
    with_delays = results[0].delays is not None
    if placed[0].local_grid is None:
        # threads: the groups are consecutive baselines whose cells hold chunk rows, so
        # their grids stacked are the chunk's grid (one numba pass to row order)
        def rows_of(cells, fill):
            return fpt.scatter_rows(tgt_grid, np.concatenate(cells), n_rows, fill)

        return RowOutputs(
            {c: rows_of([r.phasors[c] for r in results], np.complex64(0)) for c in codes},
            rows_of([r.calibrated for r in results], False),
            {c: rows_of([r.delays[c] for r in results], 0.0) for c in codes}
            if with_delays else None)
    # remote workers: each group's cells hold its own compact rows
    out = RowOutputs({c: np.zeros((n_rows, n_corr), np.complex64) for c in codes},
                     np.zeros((n_rows, n_corr), dtype=bool),
                     {c: np.zeros((n_rows, n_corr)) for c in codes} if with_delays else None)
    for where, res in zip(placed, results):
        for c in codes:
            out.phasor_rows[c][where.picked] = fpt.scatter_rows(
                where.local_grid, res.phasors[c], where.picked.size, np.complex64(0))
            if with_delays:
                out.delay_rows[c][where.picked] = fpt.scatter_rows(
                    where.local_grid, res.delays[c], where.picked.size, 0.0)
        out.calibrated[where.picked] = fpt.scatter_rows(where.local_grid, res.calibrated,
                                                        where.picked.size, False)
    return out
