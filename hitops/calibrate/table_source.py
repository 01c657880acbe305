"""The ``--reference-table`` reference source: each target chunk's correction from a table.

The reference band's CASA table, counted and transferred per antenna and target channel
by :mod:`hitops.solutions` (one :class:`~hitops.solutions.transfer.TargetWindow` per field
and target window), corrects a chunk of target rows as CASA applycal applies the
``--caltable`` table written from the same windows (hitops/solutions/apply.py; the antenna
terms gathered onto baselines by hitops/kernels/antenna_terms.py).  What it needs of the
target set is its :class:`TargetLayout`, made from the run's
:class:`~hitops.io.metadata.SetMetadata`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Tuple

import numpy as np

from ..errors import InputError
from ..io.metadata import SetMetadata
from ..solutions.api import PreparedTransfer
from ..solutions.apply import all_fields, apply_window

#: receptors (ANTENNA1's, ANTENNA2's) of each correlation type (casacore Stokes codes)
RECEPTORS = {5: (0, 0), 6: (0, 1), 7: (1, 0), 8: (1, 1),      # RR RL LR LL
             9: (0, 0), 10: (0, 1), 11: (1, 0), 12: (1, 1)}   # XX XY YX YY


@dataclass(frozen=True)
class TargetLayout:
    """What the writer needs of TARGET_MS's subtables."""

    spw_of_ddid: np.ndarray                 # (n_ddid,) SPECTRAL_WINDOW_ID
    receptors_of_ddid: Tuple[np.ndarray, ...]   # per DATA_DESC_ID: (n_corr, 2) receptor of ant1, ant2
    chan_freq: Tuple[np.ndarray, ...]       # per spectral window: (n_chan,) Hz


def target_layout(meta: SetMetadata) -> TargetLayout:
    """The layout from the target's metadata; a correlation type no antenna gain applies to
    is refused, naming the data description."""
    receptors = []
    for ddid in range(len(meta.data_descriptions)):
        types = meta.corr_types_of(ddid)
        unknown = [int(c) for c in types if int(c) not in RECEPTORS]
        if unknown:
            raise InputError(f"TARGET_MS '{meta.ms}' data description {ddid} has correlation "
                             f"type(s) {unknown} (casacore Stokes codes): a table's antenna gains "
                             "apply to RR/RL/LR/LL or XX/XY/YX/YY; give circular or linear hands")
        receptors.append(np.array([RECEPTORS[int(c)] for c in types], int))
    spw = np.array([d.window for d in meta.data_descriptions], int)
    return TargetLayout(spw, tuple(receptors),
                        tuple(np.asarray(w.chan_freq, float) for w in meta.windows))


@dataclass
class ChunkOutput:
    """One chunk's corrected visibilities per method and the samples left uncalibrated."""

    columns: Dict[str, np.ndarray]
    uncalibrated: np.ndarray    # (n_row, n_corr) bool


def window_rows(prepared: PreparedTransfer, layout: "TargetLayout", ddid: np.ndarray,
                 field: np.ndarray):
    """(index, window, receptors, rows) of every transferred window and data description
    in the chunk."""
    for j, window in enumerate(prepared.targets):
        for d in np.flatnonzero(layout.spw_of_ddid == window.spw):
            rows = np.flatnonzero((ddid == d) & (field == window.field))
            if rows.size:
                yield j, window, layout.receptors_of_ddid[d], rows


def correct_chunk(transfers: Dict[str, PreparedTransfer], layout: TargetLayout, cols: Dict) -> ChunkOutput:
    """The target rows of one chunk corrected by each method's transferred antenna terms.

    Every field's solutions of a window are one series, as applycal interpolates them
    with its default gainfield (hitops/solutions/apply.py); a window without any stays 0.
    """
    data = cols["data"]
    n_row, _, n_corr = data.shape
    ddid = cols["DATA_DESC_ID"]
    out = {m: np.zeros(data.shape, np.complex64) for m in transfers}
    calibrated = np.ones((n_row, n_corr), bool)
    for method, prepared in transfers.items():
        done = np.zeros((n_row, n_corr), bool)
        merged = all_fields(prepared.targets)
        for d in np.unique(ddid):
            window = merged.get(int(layout.spw_of_ddid[d]))
            if window is None:
                continue
            rows = np.flatnonzero(ddid == d)
            corrected = apply_window(window, cols["TIME"][rows], cols["ANTENNA1"][rows],
                                     cols["ANTENNA2"][rows], layout.receptors_of_ddid[d],
                                     data[rows], layout.chan_freq[window.spw])
            out[method][rows] = corrected.data
            done[rows] = corrected.calibrated
        calibrated &= done
    return ChunkOutput(out, ~calibrated)


