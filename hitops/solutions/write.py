"""A target-band Fringe Jones table that CASA applycal applies to every channel and window.

CASA lays the empty table out (``calibrater.createcaltable`` 'Float', 'Fringe Jones',
through :mod:`hitops.io.caltable`), with the target set's ANTENNA, FIELD and
SPECTRAL_WINDOW subtables.  Then, as fringefit leaves its own tables:

* SPECTRAL_WINDOW: one channel per window, CHAN_FREQ the window's centre (the
  frequency the FPARAM phase refers to: CASA's FringeJones evaluates
  phase + 2*pi*delay*(nu - CHAN_FREQ) per channel), CHAN_WIDTH the window's total
  bandwidth;
* one row per solution time, target window and antenna (time-major), FPARAM
  (1, 4 * n_receptor) = [phase rad, delay ns, rate s/s, 0] per receptor, FLAG on every
  parameter of a missing solution, ANTENNA2 the reference antenna, INTERVAL 0.

The phase is written unwrapped (float32 keeps 1e-5 rad at a few hundred radians), so
whatever applycal does between solutions never cuts across a wrap; between solutions it
follows the rate (docs/solutions.md).  The table is built beside ``path`` and renamed
into place when whole.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import MeasurementSetError, OutputExistsError
from ..io.atomic import replaced_directory
from ..io.caltable import _create_empty
from .read import FRINGE_PARS
from .transfer import TargetWindow
from ..io import tables
from ..io.metadata import read_metadata
from ..io.msv4.store import is_processing_set

#: receptors of a CASA Fringe Jones table (applycal aborts on a one-receptor table)
N_RECEPTOR = 2


def _set_centres(path: str, ms: str) -> None:
    """One channel per window in the table's SPECTRAL_WINDOW: the window's centre.

    createcaltable leaves one channel per window at the MS's channel n_chan/2 (227.1625
    GHz for 16 channels centred on 227.1 GHz), so the centre comes from the MS itself.
    """
    windows = read_metadata(ms).windows
    freqs = [w.chan_freq for w in windows]
    widths = [np.abs(w.chan_width) for w in windows]
    with tables.calibration_subtable(path, "SPECTRAL_WINDOW", writable=True) as t:
        for row, (freq, width) in enumerate(zip(freqs, widths)):
            centre = 0.5 * (freq.min() + freq.max())
            total = float(width.sum())
            t.putcell("NUM_CHAN", row, 1)
            for col, value in (("CHAN_FREQ", centre), ("CHAN_WIDTH", total),
                               ("EFFECTIVE_BW", total), ("RESOLUTION", total)):
                t.putcell(col, row, np.array([value]))


def _rows(windows: Sequence[TargetWindow], n_ant: int):
    """Row arrays, time-major then window then antenna."""
    keys = sorted((float(t), k, i) for k, w in enumerate(windows) for i, t in enumerate(w.times))
    # CASA's Fringe Jones has two receptors; a T Jones source (one for both) fills both
    n_rec = N_RECEPTOR
    n_row = len(keys) * n_ant
    out = {
        "TIME": np.empty(n_row), "FIELD_ID": np.empty(n_row, np.int32),
        "SPECTRAL_WINDOW_ID": np.empty(n_row, np.int32),
        "ANTENNA1": np.tile(np.arange(n_ant, dtype=np.int32), len(keys)),
        "ANTENNA2": np.empty(n_row, np.int32), "SCAN_NUMBER": np.empty(n_row, np.int32),
        "FPARAM": np.zeros((n_row, 1, FRINGE_PARS * n_rec), np.float32),
        "FLAG": np.zeros((n_row, 1, FRINGE_PARS * n_rec), bool),
        "SNR": np.zeros((n_row, 1, FRINGE_PARS * n_rec), np.float32),
    }
    for j, (time, k, i) in enumerate(keys):
        w = windows[k]
        rows = slice(j * n_ant, (j + 1) * n_ant)
        out["TIME"][rows] = time
        out["FIELD_ID"][rows] = w.field
        out["SPECTRAL_WINDOW_ID"][rows] = w.spw
        out["ANTENNA2"][rows] = w.refant[i]
        out["SCAN_NUMBER"][rows] = w.scan[i]
        for rec in range(n_rec):
            base = FRINGE_PARS * rec
            src = min(rec, w.phase.shape[2] - 1)
            ok = w.valid[i, :, src]
            out["FPARAM"][rows, 0, base] = w.phase[i, :, src]
            out["FPARAM"][rows, 0, base + 1] = w.delay_s[i, :, src] * 1e9
            out["FPARAM"][rows, 0, base + 2] = w.rate[i, :, src]
            out["FLAG"][rows, 0, base:base + FRINGE_PARS] = ~ok[:, None]
            out["SNR"][rows, 0, base:base + FRINGE_PARS] = ok[:, None].astype(np.float32)
    return out, n_row


def write_fringe_table(path, target_ms, windows: Sequence[TargetWindow], n_ant: int,
                       overwrite: bool = False) -> int:
    """Write the target-band Fringe Jones table; returns its number of rows."""
    path = Path(str(path).rstrip("/"))
    ms = str(target_ms).rstrip("/")
    # a processing set's subtables reach CASA through hitops/io/msv4/casa_view.py
    if not ((Path(ms) / "table.dat").is_file() or is_processing_set(ms)):
        raise MeasurementSetError(f"TARGET_MS '{ms}' does not exist or is not a Measurement Set")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"calibration table '{path}' exists; pass overwrite=True "
                                "(--overwrite) to replace it or choose another path")
    cols, n_row = _rows(windows, n_ant)
    with replaced_directory(path) as partial:
        _create_empty(ms, str(partial), par_type="Float", vis_cal="Fringe Jones")
        _set_centres(str(partial), ms)
        with tables.open_table(str(partial), writable=True) as t:
            t.addrows(n_row)
            for name, values in cols.items():
                t.putcol(name, values)
            t.putcol("INTERVAL", np.zeros(n_row))
            t.putcol("OBSERVATION_ID", np.zeros(n_row, np.int32))
            t.putcol("PARAMERR", np.zeros(cols["FPARAM"].shape, np.float32))
    return n_row
