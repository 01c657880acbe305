"""CASA calibration tables solved on REF_MS -> typed per-antenna solution series.

Supported types (table.info subType, the keyword VisCal):

* 'Fringe Jones' (fringefit; ParType Float): FPARAM (n_row, 1, 4 * n_receptor), per
  receptor [phase rad, delay ns, rate s/s, dispersive term]; FLAG of the same shape.
* 'G Jones' (gaincal; ParType Complex): CPARAM (n_row, 1, n_receptor), the phase is
  its angle; no delay, no rate.
* 'T Jones' (gaincal gaintype 'T'): CPARAM (n_row, 1, 1), one receptor for both hands.

One row per solution time and antenna; ANTENNA2 is the reference antenna of that
solution (fringefit changes it when the first one sets).  The solution phase refers to
the frequency in the table's SPECTRAL_WINDOW::CHAN_FREQ (one channel: the centre of
the solved window, 86.0 GHz for a 16 x 125 MHz window from 85.0625 GHz), not to
REF_FREQUENCY (the MS's first channel, 85.0625 GHz): scaling by the wrong one
measured a whole-track coherence of 0.59 instead of 0.99995 (GUIDE section 3).
CASA's own FringeJones::calcAllJones evaluates phase + 2*pi*delay*(nu - nu_ref) per
channel with nu_ref that CHAN_FREQ.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Tuple

import numpy as np

from .errors import NoSolutionsError, SolutionTableError, TableMismatchError, UnsupportedTableError
from ..io import tables
from ..io.metadata import read_metadata

SUPPORTED = ("Fringe Jones", "G Jones", "T Jones")
#: the remedy every TableMismatchError ends with
SAME_SET = "give the table that was solved on REF_MS, or the REF_MS it was solved on"
#: FPARAM entries per receptor in a Fringe Jones table: phase, delay (ns), rate (s/s), dispersive
FRINGE_PARS = 4


@dataclass(frozen=True)
class WindowSolutions:
    """The solutions of one (spectral window, field) on a (solution time, antenna, receptor) grid."""

    spw: int                  # SPECTRAL_WINDOW_ID (REF_MS's and the table's)
    field: int                # FIELD_ID
    field_name: str
    ref_freq_hz: float        # SPECTRAL_WINDOW::CHAN_FREQ of the table: what the phase refers to
    times: np.ndarray         # (n_sol,) MS TIME of the solutions, ascending
    scan: np.ndarray          # (n_sol,) int32 SCAN_NUMBER
    phase: np.ndarray         # (n_sol, n_ant, n_rec) float64 rad, NaN where there is no solution
    delay_s: np.ndarray       # (n_sol, n_ant, n_rec) float64 seconds (0 for G/T)
    rate: np.ndarray          # (n_sol, n_ant, n_rec) float64 s/s (0 for G/T)
    valid: np.ndarray         # (n_sol, n_ant, n_rec) bool: a row exists and is unflagged
    refant: np.ndarray        # (n_sol,) int32 reference antenna of each solution time (-1 none)


@dataclass(frozen=True)
class SolutionTable:
    path: str
    kind: str                 # 'Fringe Jones', 'G Jones' or 'T Jones'
    has_rates: bool
    antenna_names: Tuple[str, ...]
    n_receptor: int
    windows: Tuple[WindowSolutions, ...]


def _table_kind(path: str) -> str:
    if not (Path(path) / "table.dat").is_file():
        raise SolutionTableError(f"reference table '{path}' does not exist or is not a CASA "
                                 "table; give the table fringefit or gaincal wrote on REF_MS")
    with tables.open_table(path) as t:
        info = t.info()
        kind = info.get("subType", "") if info.get("type") == "Calibration" else ""
        if kind not in SUPPORTED:
            what = f"'{kind}' table" if kind else f"not a calibration table (type '{info.get('type', '')}')"
            raise UnsupportedTableError(
                f"reference table '{path}' is {'a ' if kind else ''}{what}; supported: "
                f"{', '.join(SUPPORTED)} (fringefit, gaincal calmode 'p', gaincal gaintype 'T')")
        if t.nrows() == 0:
            raise SolutionTableError(f"reference table '{path}' has no rows; re-run the solve")
    return kind


def _ms_meta(ms: str, meta=None):
    meta = meta if meta is not None else read_metadata(ms)
    chan_freq = [w.chan_freq for w in meta.windows]
    ref_freq = np.array([w.ref_frequency for w in meta.windows], np.float64)
    return meta.antennas.names, meta.fields.names, chan_freq, ref_freq


def _check_subtables(path: str, ms: str, names, fields, ms_chan_freq, ms_ref_freq):
    """Antennas, fields and windows of the table must be REF_MS's (CASA copies them)."""
    with tables.calibration_subtable(path, "ANTENNA") as t:
        tab_names = tuple(str(n) for n in t.getcol("NAME"))
    if tab_names != names:
        raise TableMismatchError(f"reference table '{path}' was solved on another set: its "
                                 f"antennas {list(tab_names)} are not {ms}'s {list(names)}; {SAME_SET}")
    with tables.calibration_subtable(path, "FIELD") as t:
        tab_fields = tuple(str(n) for n in t.getcol("NAME"))
    if tab_fields != fields:
        raise TableMismatchError(f"reference table '{path}' was solved on another set: its "
                                 f"fields {list(tab_fields)} are not {ms}'s {list(fields)}; {SAME_SET}")
    with tables.calibration_subtable(path, "SPECTRAL_WINDOW") as t:
        tab_ref = t.getcol("REF_FREQUENCY")
        centres = [np.asarray(t.getcell("CHAN_FREQ", i), float) for i in range(t.nrows())]
    if tab_ref.size != ms_ref_freq.size or not np.allclose(tab_ref, ms_ref_freq, rtol=1e-9):
        raise TableMismatchError(
            f"reference table '{path}' was solved on another set: its spectral windows "
            f"(REF_FREQUENCY {np.round(tab_ref / 1e9, 6).tolist()} GHz) are not {ms}'s "
            f"({np.round(ms_ref_freq / 1e9, 6).tolist()} GHz); {SAME_SET}")
    return centres


def _solution_centre(path: str, spw: int, centres, ms_chan_freq, ms: str) -> float:
    """The frequency the solution phase refers to: the table's CHAN_FREQ of the window."""
    freq = centres[spw]
    lo, hi = ms_chan_freq[spw].min(), ms_chan_freq[spw].max()
    if freq.size != 1:
        raise SolutionTableError(
            f"reference table '{path}' has {freq.size} solution channels in spectral window {spw}; "
            "a per-channel (bandpass-like) solution is not supported: solve one phase per window")
    width = np.ptp(ms_chan_freq[spw]) / max(ms_chan_freq[spw].size - 1, 1)
    if not lo - width <= freq[0] <= hi + width:
        raise TableMismatchError(
            f"reference table '{path}': spectral window {spw}'s solution frequency "
            f"{freq[0] / 1e9:.6f} GHz lies outside {ms}'s window ({lo / 1e9:.6f}-{hi / 1e9:.6f} GHz); "
            f"{SAME_SET}")
    return float(freq[0])


def _parameters(t, kind: str, rows: np.ndarray):
    """phase, delay (s), rate (s/s), valid per (row, receptor) of the selected rows."""
    if kind == "Fringe Jones":
        fpar = t.getcol("FPARAM")[rows, 0, :].astype(np.float64)
        flag = t.getcol("FLAG")[rows, 0, :]
        phase = fpar[:, 0::FRINGE_PARS]
        delay = fpar[:, 1::FRINGE_PARS] * 1e-9
        rate = fpar[:, 2::FRINGE_PARS]
        valid = ~flag[:, 0::FRINGE_PARS]
    else:
        cpar = t.getcol("CPARAM")[rows, 0, :].astype(np.complex128)
        valid = ~t.getcol("FLAG")[rows, 0, :] & (np.abs(cpar) > 0)
        phase = np.angle(cpar)
        delay = np.zeros(phase.shape)
        rate = np.zeros(phase.shape)
    return phase, delay, rate, valid & np.isfinite(phase)


def _window(t, kind, rows, spw, field, field_name, ref_freq_hz, n_ant) -> WindowSolutions:
    time = t.getcol("TIME")[rows]
    ant = t.getcol("ANTENNA1")[rows]
    ref = t.getcol("ANTENNA2")[rows]
    scan_col = t.getcol("SCAN_NUMBER")[rows]
    times, it = np.unique(time, return_inverse=True)
    phase, delay, rate, ok = _parameters(t, kind, rows)
    n_sol, n_rec = times.size, phase.shape[1]
    grid = {name: np.full((n_sol, n_ant, n_rec), fill) for name, fill in
            (("phase", np.nan), ("delay", 0.0), ("rate", 0.0))}
    valid = np.zeros((n_sol, n_ant, n_rec), bool)
    grid["phase"][it, ant] = np.where(ok, phase, np.nan)
    grid["delay"][it, ant] = np.where(ok, delay, 0.0)
    grid["rate"][it, ant] = np.where(ok, rate, 0.0)
    valid[it, ant] = ok
    scan = np.zeros(n_sol, np.int32)
    scan[it] = scan_col
    # one reference antenna per solution time: that of its unflagged rows (fringefit and
    # gaincal write the same ANTENNA2 on every row of an interval)
    refant = np.full(n_sol, -1, np.int32)
    good = ok.any(axis=1) & (ref >= 0)
    refant[it[good]] = ref[good]
    return WindowSolutions(spw=int(spw), field=int(field), field_name=field_name,
                           ref_freq_hz=ref_freq_hz, times=times, scan=scan, phase=grid["phase"],
                           delay_s=grid["delay"], rate=grid["rate"], valid=valid, refant=refant)


def _ms_time_range(ms: str):
    """(first TIME, last TIME, longest INTERVAL) of a Measurement Set or processing set."""
    from ..io.read import read_row_columns

    cols = read_row_columns(ms, ["TIME", "INTERVAL"])
    time, interval = cols["TIME"], cols["INTERVAL"]
    return float(time.min()), float(time.max()), float(np.max(interval)) if interval.size else 0.0


def _check_times(path: str, ms: str, windows) -> None:
    t_min, t_max, interval = _ms_time_range(ms)
    for w in windows:
        spacing = float(np.median(np.diff(w.times))) if w.times.size > 1 else 0.0
        slack = max(spacing, interval) + 1.0
        outside = (w.times < t_min - slack) | (w.times > t_max + slack)
        if outside.any():
            raise TableMismatchError(
                f"reference table '{path}' was solved on another set: solution time "
                f"{w.times[outside][0]:.1f} s (MJD seconds) of spectral window {w.spw} lies outside "
                f"{ms}'s {t_min:.1f}-{t_max:.1f} s; {SAME_SET}")


def _observed_antennas(ms: str, n_ant: int) -> np.ndarray:
    with tables.main_table(ms) as t:
        keep = ~t.getcol("FLAG_ROW")
        a1, a2 = t.getcol("ANTENNA1")[keep], t.getcol("ANTENNA2")[keep]
    seen = np.zeros(n_ant, bool)
    seen[a1[a1 != a2]] = True
    seen[a2[a1 != a2]] = True
    return seen


def read_solutions(path, ref_ms, ref_meta=None) -> SolutionTable:
    """Read a fringefit/gaincal table solved on ``ref_ms``; refuse one solved on another set.
    ``ref_meta``: REF_MS's :class:`~hitops.io.metadata.SetMetadata`, when already read."""
    path, ms = str(path).rstrip("/"), str(ref_ms).rstrip("/")
    if not (Path(ms) / "table.dat").is_file():
        raise SolutionTableError(f"REF_MS '{ms}' does not exist or is not a Measurement Set")
    kind = _table_kind(path)
    names, fields, ms_chan_freq, ms_ref_freq = _ms_meta(ms, ref_meta)
    centres = _check_subtables(path, ms, names, fields, ms_chan_freq, ms_ref_freq)
    windows = []
    with tables.open_table(path) as t:
        spw_col, field_col = t.getcol("SPECTRAL_WINDOW_ID"), t.getcol("FIELD_ID")
        for spw, field in sorted(set(zip(spw_col.tolist(), field_col.tolist()))):
            rows = np.flatnonzero((spw_col == spw) & (field_col == field))
            centre = _solution_centre(path, spw, centres, ms_chan_freq, ms)
            windows.append(_window(t, kind, rows, spw, field, fields[field], centre, len(names)))
    _check_times(path, ms, windows)
    any_valid = np.zeros(len(names), bool)
    for w in windows:
        any_valid |= w.valid.any(axis=(0, 2))
    missing = [names[a] for a in np.flatnonzero(_observed_antennas(ms, len(names)) & ~any_valid)]
    if missing:
        raise NoSolutionsError(
            f"reference table '{path}' has no unflagged solution for station(s) {', '.join(missing)}, "
            f"which {ms} observes; re-solve with a lower minsnr or another refant list, or flag "
            "the station(s) in both sets")
    n_rec = windows[0].phase.shape[2]
    # fringefit with zerorates=True writes rates of 0: such a table is bridged like G Jones
    has_rates = kind == "Fringe Jones" and any(bool(np.any(w.rate[w.valid])) for w in windows)
    return SolutionTable(path=path, kind=kind, has_rates=has_rates,
                         antenna_names=names, n_receptor=n_rec, windows=tuple(windows))
