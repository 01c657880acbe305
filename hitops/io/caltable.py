"""Antenna-based FPT solutions as a CASA calibration table (phase-only G Jones).

CASA's own layout is used, not imitated: ``casatools.calibrater.createcaltable``
makes the empty table exactly as ``gaincal`` does (keywords ParType 'Complex',
VisCal 'G Jones', MSName, PolBasis, the subtables ANTENNA, FIELD,
SPECTRAL_WINDOW, OBSERVATION copied from the Measurement Set and an empty
HISTORY; columns TIME, FIELD_ID, SPECTRAL_WINDOW_ID, ANTENNA1, ANTENNA2,
INTERVAL, SCAN_NUMBER, OBSERVATION_ID, CPARAM, PARAMERR, FLAG, SNR, WEIGHT in
one StandardStMan; table.info type 'Calibration', subType 'G Jones'), and the
rows are then filled with python-casacore the way ``gaincal`` fills them
(checked against a table gaincal wrote on the same set, tests/test_caltable.py):

* one row per solution time and antenna (time-major), ANTENNA1 the antenna,
  ANTENNA2 the reference antenna (-1 when there is none), INTERVAL 0 (as
  gaincal writes for ``solint='int'``), SCAN_NUMBER the Measurement Set's scan
  at that time;
* CPARAM (n_receptor = 2, n_chan = 1) per row: receptor 0 is R (or X), 1 is
  L (or Y), taken from the parallel-hand correlations RR/LL (XX/YY);
* flagged solutions hold 1+0j with FLAG set (gaincal does the same).

CASA's convention (Measurement Equation): V_obs_pq = G_p V_true_pq G_q^H and
``applycal`` divides the gains out, so CORRECTED_DATA_pq = DATA_pq /
(g_p g_q^*).  A table with CPARAM = exp(+i phi_p) therefore makes ``applycal``
multiply baseline p-q by exp(-i (phi_p - phi_q)): ``antenna_phase`` is the
phase to *remove* from the target band (tests/test_caltable.py runs CASA
applycal and checks this to 1e-6 rad on every unflagged sample).  Cross
hands get exp(-i (phi_p[R] - phi_q[L])) and its mirror, as CASA forms them.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError, MeasurementSetError, OutputExistsError
from .atomic import replaced_directory
from . import tables
from .metadata import read_metadata
from .msv4.store import is_processing_set

log = logging.getLogger("hitops.io")

#: receptor of each parallel-hand correlation: G Jones parameter 0 is R (X), 1 is L (Y)
RECEPTOR = {"RR": 0, "LL": 1, "XX": 0, "YY": 1}


def scan_of_times(ms: str, time: np.ndarray) -> np.ndarray:
    """SCAN_NUMBER of the set at each solution time (the nearest row's); the set may be an
    MSv4 processing set (:func:`hitops.io.read.read_row_columns` reads either)."""
    from .read import read_row_columns

    rows = read_row_columns(ms, ["TIME", "SCAN_NUMBER"])
    ms_time, ms_scan = rows["TIME"], rows["SCAN_NUMBER"]
    order = np.argsort(ms_time, kind="stable")
    ms_time, ms_scan = ms_time[order], ms_scan[order]
    if ms_time.size == 0:
        return np.ones(time.size, np.int32)
    idx = np.clip(np.searchsorted(ms_time, time), 1, ms_time.size - 1) if ms_time.size > 1 \
        else np.zeros(time.size, np.int64)
    if ms_time.size > 1:
        left = idx - 1
        idx = np.where(np.abs(ms_time[left] - time) <= np.abs(ms_time[idx] - time), left, idx)
    return ms_scan[idx].astype(np.int32)


def write_gain_table(path, ms, time, antenna_phase, valid, corr_names: Sequence[str],
                     overwrite: bool = False, spw: int = 0, field: int = 0,
                     refant: int = -1, scan: Optional[np.ndarray] = None,
                     snr: Optional[np.ndarray] = None) -> str:
    """Write a phase-only G Jones table that CASA ``applycal`` and ``plotms`` accept.

    ``path``: the table to write (a directory; replaced only with ``overwrite``).
    ``ms``: the Measurement Set the solutions belong to (the target band); its
    ANTENNA, FIELD, SPECTRAL_WINDOW and OBSERVATION subtables are copied, and
    antenna indices are its ANTENNA rows.
    ``time``: (n_time,) solution times, MS TIME (UTC seconds, MJD scale).
    ``antenna_phase``: float64 radians, (n_time, n_ant, n_corr): the phase to
    remove from the target band, so applycal multiplies baseline p-q by
    exp(-i (phi_p - phi_q)).  ``valid``: bool of the same shape (None: all
    finite values); invalid solutions are written flagged, and applycal
    (applymode 'calflag') flags the data they touch.
    ``corr_names``: the correlation of each last-axis entry ('RR', 'LL', 'XX',
    'YY'; cross hands are accepted and ignored: CASA forms them from the
    receptors).  ``spw``, ``field``: SPECTRAL_WINDOW_ID and FIELD_ID of every
    row.  ``refant``: antenna index written as ANTENNA2 (-1: none).  ``scan``:
    (n_time,) SCAN_NUMBER per solution (default: the MS's at each time).
    ``snr``: optional (n_time, n_ant, n_corr) SNR column values (default 1
    for valid solutions, 0 for flagged ones).  Returns the path written.

    The table is built under a temporary name beside ``path`` and renamed into
    place last, so a failure leaves nothing that looks like a result.
    """
    path = Path(str(path).rstrip("/"))
    ms = str(ms).rstrip("/")
    if not ((Path(ms) / "table.dat").is_file() or is_processing_set(ms)):
        raise MeasurementSetError(f"caltable: Measurement Set '{ms}' does not exist or is "
                                  "not a table")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"calibration table '{path}' exists; pass --overwrite to "
                                "replace it or choose another --caltable path")
    time = np.asarray(time, dtype=np.float64).ravel()
    phase = np.asarray(antenna_phase, dtype=np.float64)
    corr_names = [str(c).upper() for c in corr_names]
    if phase.ndim != 3 or phase.shape[0] != time.size or phase.shape[2] != len(corr_names):
        raise InputError(f"caltable: antenna_phase has shape {phase.shape}; expected "
                         f"(n_time={time.size}, n_ant, n_corr={len(corr_names)})")
    n_time, n_ant, _ = phase.shape
    if is_processing_set(ms):
        n_ms_ant = read_metadata(ms).antennas.n_ant
    else:
        with tables.subtable(ms, "ANTENNA") as t:
            n_ms_ant = t.nrows()
    if n_ant != n_ms_ant:
        raise InputError(f"caltable: {n_ant} antennas in the solutions, {n_ms_ant} in "
                         f"{ms}::ANTENNA; give one entry per ANTENNA row")
    valid = (np.isfinite(phase) if valid is None
             else np.asarray(valid, dtype=bool) & np.isfinite(phase))
    if valid.shape != phase.shape:
        raise InputError(f"caltable: valid has shape {valid.shape}, antenna_phase {phase.shape}")
    parallel = {c: k for k, c in enumerate(corr_names) if c in RECEPTOR}
    if not parallel:
        raise InputError(f"caltable: no parallel-hand correlation among {corr_names}; a G "
                         "Jones table needs RR/LL or XX/YY solutions")
    if scan is None:
        scan = scan_of_times(ms, time)
    scan = np.asarray(scan, dtype=np.int32).ravel()
    if scan.size != n_time:
        raise InputError(f"caltable: {scan.size} scan numbers for {n_time} solution times")

    # per receptor: phase and validity (a receptor without a correlation: unit gain, unflagged,
    # so it changes nothing; there are then no data on it to apply to)
    cparam = np.ones((n_time, n_ant, 1, 2), np.complex64)
    flag = np.zeros((n_time, n_ant, 1, 2), bool)
    snr_out = np.zeros((n_time, n_ant, 1, 2), np.float32)
    for corr, k in parallel.items():
        rec = RECEPTOR[corr]
        ok = valid[:, :, k]
        cparam[:, :, 0, rec] = np.where(ok, np.exp(1j * np.where(ok, phase[:, :, k], 0.0)), 1.0)
        flag[:, :, 0, rec] = ~ok
        if snr is not None:
            snr_out[:, :, 0, rec] = np.where(ok, np.asarray(snr, np.float32)[:, :, k], 0.0)
        else:
            snr_out[:, :, 0, rec] = ok.astype(np.float32)
    n_row = n_time * n_ant

    with replaced_directory(path) as partial:
        _create_empty(ms, str(partial))
        with tables.open_table(str(partial), writable=True) as t:
            t.addrows(n_row)
            t.putcol("TIME", np.repeat(time, n_ant))
            t.putcol("FIELD_ID", np.full(n_row, int(field), np.int32))
            t.putcol("SPECTRAL_WINDOW_ID", np.full(n_row, int(spw), np.int32))
            t.putcol("ANTENNA1", np.tile(np.arange(n_ant, dtype=np.int32), n_time))
            t.putcol("ANTENNA2", np.full(n_row, int(refant), np.int32))
            t.putcol("INTERVAL", np.zeros(n_row))
            t.putcol("SCAN_NUMBER", np.repeat(scan, n_ant))
            t.putcol("OBSERVATION_ID", np.zeros(n_row, np.int32))
            t.putcol("CPARAM", cparam.reshape(n_row, 1, 2))
            t.putcol("PARAMERR", np.zeros((n_row, 1, 2), np.float32))
            t.putcol("FLAG", flag.reshape(n_row, 1, 2))
            t.putcol("SNR", snr_out.reshape(n_row, 1, 2))
    log.info("wrote calibration table %s: %d times x %d antennas, %.1f%% of solutions flagged",
             path, n_time, n_ant, 100.0 * float(flag[..., [RECEPTOR[c] for c in parallel]].mean()))
    return str(path)


def _create_empty(ms: str, path: str, par_type: str = "Complex", vis_cal: str = "G Jones") -> None:
    """An empty table laid out by CASA itself (calibrater.createcaltable): G Jones by
    default; hitops.solutions.write makes a 'Float' 'Fringe Jones' one.  From an MSv4
    processing set, CASA reads its subtables through a Measurement Set v2 of no rows
    (hitops/io/msv4/casa_view.py), and the table's MSName names the store."""
    if is_processing_set(ms):
        from .msv4.casa_view import casa_view

        with casa_view(ms) as view:
            _create_from_ms(view, path, par_type, vis_cal)
        with tables.open_table(path, writable=True) as t:
            t.putkeyword("MSName", ms)
        return
    _create_from_ms(ms, path, par_type, vis_cal)


def _create_from_ms(ms: str, path: str, par_type: str, vis_cal: str) -> None:
    from ..casa_env import ensure_casa_offline

    ensure_casa_offline()
    # casatasks sets up CASA's log sink (INFO lines off the console, as for hitops.casa tasks)
    import casatasks  # noqa: F401
    import casatools

    cb = casatools.calibrater()
    try:
        # open without adding MODEL_DATA/CORRECTED_DATA: the set is not changed
        if not cb.open(ms, False, False, False):
            raise MeasurementSetError(f"CASA cannot open '{ms}' for calibration")
        cb.createcaltable(path, par_type, vis_cal, True)
    finally:
        cb.close()
        cb.done()
    if not (Path(path) / "table.dat").is_file():
        raise MeasurementSetError(f"CASA did not create the calibration table '{path}' "
                                  f"from '{ms}'")

