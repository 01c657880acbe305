"""A calibrated band as UVFITS (random groups) for eht-imaging, AIPS and DIFMAP.

:func:`export_uvfits` writes any complex column of a single-field Measurement
Set (e.g. ``PWC_DATA``), or any data group of an MSv4 processing set (``pwc``:
hitops/io/msv4/uvfits_rows.py reads it as the same rows), as the visibilities
of a UVFITS file.  CASA ``exportuvfits`` only exports DATA, CORRECTED_DATA or
MODEL_DATA and took ~5 s for a 1.2 M-row band (this writer: about 1 s,
docs/interop.md); writing the file here reads the column directly and never
touches the Measurement Set.

The layout follows CASA's exportuvfits and the EHT's public UVFITS files
(which eht-imaging, AIPS and DIFMAP all load):

* primary random groups, BITPIX -32, axes COMPLEX (re, im, weight), STOKES,
  FREQ, IF (1), RA, DEC; one source (OBJECT, OBSRA/OBSDEC and CRVAL6/7, no
  SOURCE parameter), one frequency setup (no FREQSEL parameter);
* group parameters UU---SIN, VV---SIN, WW---SIN (seconds: UVW / c, the
  Measurement Set's sign, as CASA writes them), BASELINE = 256 a1 + a2
  (1-based ANTENNA rows), DATE as two parameters (Julian day at 0h and the day
  fraction: eht-imaging ignores PZERO), INTTIM;
* rows sorted by time then baseline ('TB', AIPS's sort order);
* flagged samples (FLAG, FLAG_ROW, or non-finite data) keep their value
  (0 when non-finite) with a negative weight: AIPS, DIFMAP, eht-imaging and
  CASA importuvfits all read weight <= 0 as flagged;
* tables AIPS AN (stations: ANNAME = hitops's station code, ITRF STABXYZ,
  NOSTA, mount, feeds R/L or X/Y, DIAMETER), AIPS FQ (one row) and AIPS NX
  (one row per SCAN_NUMBER run, which eht-imaging reads as its scan table).

Correlations are written in AIPS order (RR, LL, RL, LR = -1..-4; XX, YY, XY,
YX = -5..-8; I, Q, U, V = 1..4); a correlation missing from a regular run
(e.g. RR and RL only) is written as zero with zero weight.

FITS itself is written with numpy (:mod:`hitops.io.fits`: 2880-byte blocks of
80-character cards, big-endian data), so the package needs no FITS library;
the tests read the files back with astropy, CASA importuvfits and eht-imaging.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

from ..errors import InputError, MeasurementSetError, OutputExistsError
from .fits import bintable, card, gst0_deg, header_bytes, iso_date, pad, tai_minus_utc
from .msv4.store import is_processing_set
from .uvfits_ms import AIPS_STOKES, MainRows, Setup, read_main, read_setup

log = logging.getLogger("hitops.io")

C_LIGHT = 299792458.0
MOUNT_CODES = {"alt-az": 0, "equatorial": 1, "x-y": 3, "orbiting": 2, "spherical": 4,
               "alt-az+nasmyth-r": 4, "alt-az+nasmyth-l": 5}


# ---------------------------------------------------------------- the set

def _check_destination(ms: str, path: Path, overwrite: bool, role: str) -> None:
    if path.exists() and not overwrite:
        raise OutputExistsError(f"UVFITS file '{path}' exists; pass --overwrite to replace it "
                                "or give another --export-uvfits path")
    if path.is_dir():
        raise InputError(f"--export-uvfits '{path}' is a directory; give a file name "
                         "(e.g. target-pwc.uvfits)")
    if not ((Path(ms) / "table.dat").is_file() or is_processing_set(ms)):
        raise MeasurementSetError(f"{role} '{ms}' does not exist or is not a table")


# ---------------------------------------------------------------- the random groups

@dataclass(frozen=True)
class _StokesAxis:
    """The STOKES axis: AIPS codes from the first down (or up), each column's place on it."""

    codes: List[int]
    step: int
    slot: List[int]                          # axis index of each correlation of the column

    @classmethod
    def of(cls, corr_types: Sequence[int]) -> "_StokesAxis":
        aips = [AIPS_STOKES[c] for c in corr_types]
        if min(aips) > 0:
            codes, step = list(range(min(aips), max(aips) + 1)), 1
        else:
            codes, step = list(range(max(aips), min(aips) - 1, -1)), -1
        return cls(codes, step, [codes.index(a) for a in aips])


@dataclass(frozen=True)
class _Groups:
    """The random-group data in time-baseline order, and what the tables need of it."""

    data: np.ndarray                         # (n_group, 7 + n_if * n_chan * n_stokes * 3) big-endian
    flag: np.ndarray                         # (n_group, n_if, n_chan, n_corr) written as flagged
    jd0: float                               # Julian day at 0h of the first time
    time: np.ndarray                         # TIME (s) in file order
    interval: np.ndarray
    scan: np.ndarray                         # SCAN_NUMBER in file order


def _group_index(main: MainRows, setup: Setup):
    """(row order, group of each ordered row, IF of each ordered row, first row of each group):
    one random group per (time, baseline), each data description's row filling its IF
    (the windows' rows of one integration carry the same TIME, as correlators write them)."""
    cols = main.cols
    if_of_dd = {dd: i for i, dd in enumerate(setup.ddids)}
    row_if = np.array([if_of_dd[int(d)] for d in cols["DATA_DESC_ID"]], np.int64)
    order = np.lexsort((row_if, cols["ANTENNA2"], cols["ANTENNA1"], cols["TIME"]))
    keys = np.stack([cols["TIME"][order], cols["ANTENNA1"][order], cols["ANTENNA2"][order]])
    new = np.ones(order.size, bool)
    new[1:] = (keys[:, 1:] != keys[:, :-1]).any(axis=0)
    return order, np.cumsum(new) - 1, row_if[order], order[new]


def _random_groups(main: MainRows, setup: Setup, stokes: _StokesAxis) -> _Groups:
    """Parameters (u, v, w, baseline, date, inttim) then the (n_if, n_chan, n_stokes, 3) cube."""
    cols, n_corr = main.cols, len(stokes.slot)
    n_if, n_chan = setup.n_if, setup.n_chan
    order, group, row_if, first = _group_index(main, setup)
    n_row, n_group = order.size, first.size
    vis = np.asarray(main.vis)[order].reshape(n_row, n_chan, n_corr)
    flag = (cols["FLAG"][order].reshape(n_row, n_chan, n_corr)
            | cols["FLAG_ROW"][order][:, None, None] | ~np.isfinite(vis))
    if main.weight_spectrum is not None:
        weight = np.asarray(main.weight_spectrum, np.float32)[order].reshape(n_row, n_chan, -1)
    else:
        weight = np.broadcast_to(cols["WEIGHT"][order].astype(np.float32)[:, None, :],
                                 (n_row, n_chan, n_corr))
    weight = np.abs(np.nan_to_num(weight, nan=0.0, posinf=0.0))
    # flagged samples keep their value with a negative weight (read as flagged everywhere)
    weight = np.where(flag, -np.maximum(weight, 1e-30), weight).astype(np.float32)
    values = np.where(np.isfinite(vis), vis, 0)

    time_ = cols["TIME"][first]
    jd = time_ / 86400.0 + 2400000.5
    jd0 = math.floor(float(jd.min()) - 0.5) + 0.5
    day = np.floor(jd - jd0)
    uvw_s = cols["UVW"][first] / C_LIGHT
    params = np.empty((n_group, 7), ">f4")
    params[:, 0] = uvw_s[:, 0]
    params[:, 1] = uvw_s[:, 1]
    params[:, 2] = uvw_s[:, 2]
    params[:, 3] = 256 * (cols["ANTENNA1"][first].astype(np.int64) + 1) + \
        (cols["ANTENNA2"][first].astype(np.int64) + 1)
    params[:, 4] = jd0 + day
    params[:, 5] = jd - jd0 - day
    params[:, 6] = cols["INTERVAL"][first]
    # a (time, baseline) without a row in some window: zero with zero weight there
    cube = np.zeros((n_group, n_if, n_chan, len(stokes.codes), 3), ">f4")
    group_flag = np.ones((n_group, n_if, n_chan, n_corr), bool)
    group_flag[group, row_if] = flag
    for k, s in enumerate(stokes.slot):
        cube[group, row_if, :, s, 0] = values[:, :, k].real
        cube[group, row_if, :, s, 1] = values[:, :, k].imag
        cube[group, row_if, :, s, 2] = weight[:, :, k]
    # one big-endian block (np.concatenate would return native byte order)
    groups = np.empty((n_group, params.shape[1] + cube[0].size), ">f4")
    groups[:, :params.shape[1]] = params
    groups[:, params.shape[1]:] = cube.reshape(n_group, -1)
    return _Groups(groups, group_flag, jd0, time_, cols["INTERVAL"][first],
                   cols["SCAN_NUMBER"][first])


# ---------------------------------------------------------------- headers and tables

def _primary_cards(setup: Setup, stokes: _StokesAxis, groups: _Groups,
                   history: Sequence[str]) -> List[str]:
    """The random-groups header: axes, the 7 parameters, the source, the history lines."""
    n_row, n_chan = groups.data.shape[0], setup.n_chan
    ra_deg = math.degrees(float(setup.direction[0])) % 360.0
    dec_deg = math.degrees(float(setup.direction[1]))
    telescope = setup.telescope
    cards = [
        card("SIMPLE", True), card("BITPIX", -32), card("NAXIS", 7),
        card("NAXIS1", 0, "random groups, not an image"), card("NAXIS2", 3),
        card("NAXIS3", len(stokes.codes)), card("NAXIS4", n_chan), card("NAXIS5", setup.n_if),
        card("NAXIS6", 1), card("NAXIS7", 1), card("EXTEND", True),
        card("BLOCKED", True), card("GROUPS", True, "random group UV data"),
        card("PCOUNT", 7), card("GCOUNT", n_row),
        card("OBJECT", setup.source), card("OBSRA", ra_deg), card("OBSDEC", dec_deg),
        card("EPOCH", 2000.0), card("EQUINOX", 2000.0),
        card("DATE-OBS", iso_date(groups.jd0)), card("MJD", float(groups.jd0 - 2400000.5)),
        card("TELESCOP", telescope), card("INSTRUME", telescope),
        card("OBSERVER", setup.observer), card("BSCALE", 1.0), card("BZERO", 0.0),
        card("BUNIT", "UNCALIB"), card("VELREF", 3), card("ALTRPIX", 1.0),
        card("ALTRVAL", 0.0), card("SPECSYS", "TOPOCENT"),
    ]
    axes = [("COMPLEX", 1.0, 1.0), ("STOKES", float(stokes.codes[0]), float(stokes.step)),
            ("FREQ", float(setup.chan_freq[0, 0]), _channel_width(setup)), ("IF", 1.0, 1.0),
            ("RA", ra_deg, 1.0), ("DEC", dec_deg, 1.0)]
    for k, (ctype, crval, cdelt) in enumerate(axes, start=2):
        cards += [card(f"CTYPE{k}", ctype), card(f"CRVAL{k}", crval),
                  card(f"CDELT{k}", cdelt), card(f"CRPIX{k}", 1.0), card(f"CROTA{k}", 0.0)]
    for k, (ptype, comment) in enumerate([("UU---SIN", "u (s)"), ("VV---SIN", "v (s)"),
                                          ("WW---SIN", "w (s)"),
                                          ("BASELINE", "256 ant1 + ant2"),
                                          ("DATE", "Julian day at 0h"),
                                          ("DATE", "day fraction"),
                                          ("INTTIM", "integration (s)")], start=1):
        cards += [card(f"PTYPE{k}", ptype, comment), card(f"PSCAL{k}", 1.0),
                  card(f"PZERO{k}", 0.0)]
    cards.append(card("HISTORY", "AIPS SORT ORDER='TB'"))
    cards.append(card("SORTORD", "TB"))
    for line in history:
        for i in range(0, len(line), 70):
            cards.append(card("HISTORY", line[i:i + 70]))
    return cards


def _channel_width(setup: Setup) -> float:
    return float(setup.chan_width[0, 0]) if setup.chan_width.size else float(setup.total_bw[0])


def _an_table(setup: Setup, stokes: _StokesAxis, jd0: float) -> bytes:
    """AIPS AN: the stations (ANNAME = hitops's station code) and the array's time system."""
    n_ant = setup.n_ant
    receptors = ("X", "Y") if min(stokes.codes) <= -5 else ("R", "L")
    return bintable("AIPS AN", [
        ("ANNAME", "8A", "", setup.codes),
        ("STABXYZ", "3D", "METERS", np.asarray(setup.positions, np.float64)),
        ("ORBPARM", "0D", "", None),
        ("NOSTA", "1J", "", np.arange(1, n_ant + 1)),
        ("MNTSTA", "1J", "", [MOUNT_CODES.get(m, 0) for m in setup.mounts]),
        ("STAXOF", "1E", "METERS", np.zeros(n_ant)),
        ("POLTYA", "1A", "", [receptors[0]] * n_ant),
        ("POLAA", "1E", "DEGREES", np.zeros(n_ant)),
        ("POLCALA", "1E", "", np.zeros(n_ant)),
        ("POLTYB", "1A", "", [receptors[1]] * n_ant),
        ("POLAB", "1E", "DEGREES", np.full(n_ant, 90.0)),
        ("POLCALB", "1E", "", np.zeros(n_ant)),
        ("DIAMETER", "1E", "METERS", np.asarray(setup.diameters, np.float64)),
    ], [("ARRAYX", 0.0), ("ARRAYY", 0.0), ("ARRAYZ", 0.0), ("GSTIA0", gst0_deg(jd0)),
        ("DEGPDY", 360.9856449733), ("FREQ", float(setup.chan_freq[0, 0])),
        ("RDATE", iso_date(jd0)), ("POLARX", 0.0), ("POLARY", 0.0), ("UT1UTC", 0.0),
        ("IATUTC", tai_minus_utc(jd0 - 2400000.5)), ("TIMSYS", "UTC"),
        ("ARRNAM", setup.telescope), ("XYZHAND", "RIGHT"), ("FRAME", "ITRF"), ("NUMORB", 0),
        ("NO_IF", setup.n_if), ("NOPCAL", 0), ("POLTYPE", "APPROX"), ("FREQID", 1)], n_ant)


def _fq_table(setup: Setup) -> bytes:
    """AIPS FQ: the one frequency setup, each IF's first channel as an offset from CRVAL."""
    n_if = setup.n_if
    return bintable("AIPS FQ", [
        ("FRQSEL", "1J", "", [1]),
        ("IF FREQ", f"{n_if}D", "HZ", [setup.chan_freq[:, 0] - setup.chan_freq[0, 0]]),
        ("CH WIDTH", f"{n_if}E", "HZ", [setup.chan_width[:, 0]]),
        ("TOTAL BANDWIDTH", f"{n_if}E", "HZ", [setup.total_bw]),
        ("SIDEBAND", f"{n_if}J", "", [np.where(setup.sideband >= 0, 1, -1)]),
    ], [("NO_IF", n_if)], 1)


def _nx_table(groups: _Groups) -> Tuple[bytes, int]:
    """AIPS NX: one row per run of SCAN_NUMBER in time order; (the HDU, the number of scans)."""
    time_, scan, n_row = groups.time, groups.scan, groups.time.size
    starts = np.concatenate([[0], np.flatnonzero(np.diff(scan) != 0) + 1])
    stops = np.concatenate([starts[1:], [n_row]])
    half = groups.interval / 2.0
    t_lo = np.array([(time_[a:b] - half[a:b]).min() for a, b in zip(starts, stops)])
    t_hi = np.array([(time_[a:b] + half[a:b]).max() for a, b in zip(starts, stops)])
    mjd0 = groups.jd0 - 2400000.5
    hdu = bintable("AIPS NX", [
        ("TIME", "1E", "DAYS", ((t_lo + t_hi) / 2.0) / 86400.0 - mjd0),
        ("TIME INTERVAL", "1E", "DAYS", (t_hi - t_lo) / 86400.0),
        ("SOURCE ID", "1J", "", np.ones(starts.size)),
        ("SUBARRAY", "1J", "", np.ones(starts.size)),
        ("FREQ ID", "1J", "", np.ones(starts.size)),
        ("START VIS", "1J", "", starts + 1),
        ("END VIS", "1J", "", stops),
    ], [], starts.size)
    return hdu, int(starts.size)


def _write_whole(path: Path, header: bytes, groups: np.ndarray, tables: Sequence[bytes]) -> None:
    """The file under a temporary name, renamed when complete (a failure leaves nothing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with open(partial, "wb") as fh:
            fh.write(header)
            data = groups.tobytes()
            fh.write(data)
            fh.write(pad(len(data)))
            for table in tables:
                fh.write(table)
        partial.replace(path)
    except BaseException:
        try:
            partial.unlink()
        except OSError:
            pass
        raise


# ---------------------------------------------------------------- export

def _read_set(ms: str, column: str, role: str) -> Tuple[MainRows, Setup, str]:
    """(rows, setup, what was read) of a Measurement Set v2's ``column`` or of the data group
    it names in an MSv4 processing set (hitops/io/msv4/uvfits_rows.py): the same file."""
    if is_processing_set(ms):
        from .msv4.uvfits_rows import read_group_rows, read_group_setup
        from .msv4.columns import group_of_column

        role = "MSv4 processing set" if role == "Measurement Set" else role

        main = read_group_rows(ms, column, role)
        return main, read_group_setup(ms, main, role), f"data group {group_of_column(column)}"
    main = read_main(ms, column, role)
    return main, read_setup(ms, main, role), f"column {column}"


def export_uvfits(ms, path, column: str = "DATA", overwrite: bool = False,
                  role: str = "Measurement Set", history: Sequence[str] = ()) -> Dict:
    """Write ``column`` of ``ms`` (flags and weights kept) as the UVFITS file ``path``.

    ``ms`` must hold one field; its spectral windows become IFs.  It may be an
    MSv4 processing set, whose data group ``column`` names is written (PWC_DATA ->
    ``pwc``, DATA -> ``base``: hitops/io/msv4/columns.py).  ``path`` is replaced only with ``overwrite``; the file is
    written under a temporary name and renamed, so a failure leaves nothing.
    The Measurement Set is only read.  Returns a summary (rows, flagged
    fraction, scans, seconds).
    """
    started = time.perf_counter()
    ms = str(ms).rstrip("/")
    path = Path(path)
    _check_destination(ms, path, overwrite, role)
    main, setup, source = _read_set(ms, column, role)
    stokes = _StokesAxis.of(setup.corr_types)
    groups = _random_groups(main, setup, stokes)
    cards = _primary_cards(setup, stokes, groups,
                           [f"hitops: visibilities from {source} of {Path(ms).name}", *history])
    nx, n_scans = _nx_table(groups)
    _write_whole(path, header_bytes(cards), groups.data,
                 [_an_table(setup, stokes, groups.jd0), _fq_table(setup), nx])
    n_row, flag = groups.data.shape[0], groups.flag
    n_flagged = int(flag.sum())
    seconds = time.perf_counter() - started
    summary = {"path": str(path), "column": column, "rows": int(n_row),
               "samples": int(flag.size), "flagged": n_flagged,
               "flagged_fraction": n_flagged / max(flag.size, 1), "scans": n_scans,
               "stokes": stokes.codes, "seconds": seconds}
    log.info("wrote %s: %s of %s, %d rows, %d scans, %.1f%% flagged (negative weights), "
             "%.2f s", path, source, ms, n_row, n_scans, 100.0 * summary["flagged_fraction"],
             seconds)
    return summary


def export_cab(ms: str, uvfits: str, column: str = "PWC_DATA", overwrite: bool = False) -> Dict:
    """``hitops.export-uvfits`` (cabs/interop.yml): plain values for Stimela's python flavour."""
    out = export_uvfits(ms, uvfits, column, overwrite=bool(overwrite))
    return {"uvfits": out["path"], "rows": int(out["rows"]), "scans": int(out["scans"]),
            "flagged_fraction": float(out["flagged_fraction"])}
