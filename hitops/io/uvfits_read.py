"""The direct UVFITS reader: a plain UVFITS file into a Measurement Set without CASA.

A *plain* file (one source, one IF, one channel, circular or linear
correlations, ``BASELINE`` and ``DATE`` random-group parameters, UTC times,
weights present) is read here with numpy and written with
:mod:`hitops.io.ms_create`: about 4x faster than CASA ``importuvfits`` and no
casatasks start-up (docs/interop.md).  It keeps the file's AIPS NX scan table
(which CASA ignores) and puts the station codes (AIPS ANNAME) in
``ANTENNA::NAME``.  Anything else raises :class:`NeedsCasa`, and
:mod:`hitops.io.convert` hands the file to CASA ``importuvfits``; the tests
(tests/test_convert.py) check that both give the same set.

The layout read is the AIPS one (AIPS Memo 117, "Going AIPS FITS"): random
groups with a COMPLEX (re, im, weight) axis, BASELINE = 256 a1 + a2, DATE in
Julian days (split over one or two parameters), u, v, w in seconds; an AIPS AN
table with the stations, optional AIPS FQ, SU and NX tables.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import InputError
from .ms_create import CORR_CODES, ArrayLayout, Band, Field, create_ms

C_LIGHT = 299792458.0
#: AIPS STOKES axis value -> correlation name (the ones hitops calibrate transfers)
_AIPS_CORR = {-1: "RR", -2: "LL", -3: "RL", -4: "LR", -5: "XX", -6: "YY", -7: "XY", -8: "YX"}
_FITS_DTYPES = {8: "u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
#: binary-table TFORM codes read here (P/Q heap columns and bit arrays are left to CASA)
_TFORM = {"A": "S", "L": "S1", "B": "u1", "I": ">i2", "J": ">i4", "K": ">i8", "E": ">f4",
          "D": ">f8", "C": ">c8", "M": ">c16"}
#: telescope names CASA's Observatories table knows; others are written as VLBA (CASA
#: listobs refuses unknown names, e.g. 'EHT')
_CASA_TELESCOPES = {"VLBA", "ALMA", "VLA", "EVLA", "SMA", "ATCA", "MEERKAT", "GMRT", "WSRT",
                    "NOEMA", "IRAM PDB", "KVN", "JCMT", "APEX", "LOFAR", "NRO"}
#: axes a plain file may have (an axis of length 1 without a name is harmless too)
_KNOWN_AXES = {"COMPLEX", "STOKES", "FREQ", "IF", "RA", "DEC"}


class NeedsCasa(Exception):
    """The file uses a UVFITS feature the direct reader leaves to CASA importuvfits."""


@dataclass(frozen=True)
class UvfitsContents:
    """Everything :func:`hitops.io.ms_create.create_ms` needs, read from a plain file."""

    layout: ArrayLayout
    band: Band
    field: Field
    main: Dict[str, np.ndarray]         # main-table columns by name (no SCAN_NUMBER)
    telescope: str                      # a name CASA knows
    nx: Optional[Dict[str, np.ndarray]]  # the AIPS NX (scan) table's columns, if any


def _read_bintable(path: str, header: Dict, offset: int) -> Dict[str, np.ndarray]:
    """Columns of a FITS binary table (fixed-width columns only)."""
    n_row = int(header.get("NAXIS2", 0))
    width = int(header.get("NAXIS1", 0))
    fields = []
    pos = 0
    for k in range(1, int(header.get("TFIELDS", 0)) + 1):
        name = str(header.get(f"TTYPE{k}", f"col{k}")).strip()
        form = str(header.get(f"TFORM{k}", "")).strip()
        digits = "".join(ch for ch in form if ch.isdigit())
        code = form[len(digits):len(digits) + 1]
        count = int(digits) if digits else 1
        if code not in _TFORM:
            raise NeedsCasa(f"table column {name} has format {form}")
        if code == "A":
            dtype, size = f"S{count}", count
        else:
            base = np.dtype(_TFORM[code])
            dtype, size = ((base, (count,)) if count != 1 else base), base.itemsize * count
        if count:
            fields.append((name, pos, dtype))
        pos += size
    if pos != width:
        raise NeedsCasa(f"binary table width {width} != {pos}")
    dt = np.dtype({"names": [f[0] for f in fields], "formats": [f[2] for f in fields],
                   "offsets": [f[1] for f in fields], "itemsize": width})
    raw = np.fromfile(path, dtype=dt, count=n_row, offset=offset)
    return {name: raw[name] for name in dt.names}


# ---------------------------------------------------------------- the primary HDU

@dataclass(frozen=True)
class _Axis:
    """One axis of the random-group array (CTYPEn, NAXISn, CRVALn, CDELTn, CRPIXn)."""

    name: str
    length: int
    crval: float
    cdelt: float
    crpix: float

    def value(self, pixel: float) -> float:
        """The axis value at the 1-based ``pixel``."""
        return self.crval + (pixel - self.crpix) * self.cdelt


def _axes(h: Dict) -> List[_Axis]:
    """The array's axes after the first; NeedsCasa unless COMPLEX x 3 and one FREQ and IF."""
    axes = [_Axis(str(h.get(f"CTYPE{k}", "")).strip(), int(h[f"NAXIS{k}"]),
                  float(h.get(f"CRVAL{k}", 0.0)), float(h.get(f"CDELT{k}", 1.0)),
                  float(h.get(f"CRPIX{k}", 1.0))) for k in range(2, int(h["NAXIS"]) + 1)]
    names = [a.name for a in axes]
    # an axis of length 1 without a name (EHT-HOPS files leave CTYPE5 out) is harmless
    if any(a.name not in _KNOWN_AXES and not (a.name == "" and a.length == 1) for a in axes):
        raise NeedsCasa(f"axes {names}")
    size = {a.name: a.length for a in axes}
    if size.get("COMPLEX") != 3 or size.get("FREQ", 1) != 1 or size.get("IF", 1) != 1:
        raise NeedsCasa(f"axis lengths {size}")
    return axes


def _axis(axes: List[_Axis], name: str) -> Optional[_Axis]:
    return next((a for a in axes if a.name == name), None)


def _correlations(axes: List[_Axis]) -> List[str]:
    """The correlation of each STOKES pixel; NeedsCasa unless all circular or all linear."""
    stokes = _axis(axes, "STOKES") or _Axis("STOKES", 1, -1.0, -1.0, 1.0)
    codes = [int(round(stokes.value(i + 1))) for i in range(stokes.length)]
    if any(c not in _AIPS_CORR for c in codes):
        raise NeedsCasa(f"Stokes codes {codes}")
    corr = [_AIPS_CORR[c] for c in codes]
    if len(set(corr)) != len(corr) or not set(corr) <= {"RR", "LL", "RL", "LR"} and \
            not set(corr) <= {"XX", "YY", "XY", "YX"}:
        raise NeedsCasa(f"correlations {corr}")
    return corr


@dataclass(frozen=True)
class _Groups:
    """The random groups, memory-mapped: PCOUNT parameters then the array of each group."""

    header: Dict
    ptypes: List[str]                   # PTYPEn, upper case
    raw: np.ndarray                     # (GCOUNT, PCOUNT + array size), the file's dtype

    @property
    def pcount(self) -> int:
        return len(self.ptypes)

    def par(self, k: int) -> np.ndarray:
        """Parameter ``k`` (0-based) scaled: value * PSCAL + PZERO, float64."""
        scale = float(self.header.get(f"PSCAL{k + 1}", 1.0))
        zero = float(self.header.get(f"PZERO{k + 1}", 0.0))
        return self.raw[:, k].astype(np.float64) * scale + zero

    def find(self, prefix: str) -> List[int]:
        """Indices of the parameters named ``prefix`` (UU---SIN counts as UU, etc.)."""
        return [k for k, p in enumerate(self.ptypes) if p == prefix or p.startswith(prefix + "-")
                or (prefix in ("UU", "VV", "WW") and p.startswith(prefix))]


def _groups(path: str, hdus, axes: List[_Axis]) -> _Groups:
    h = hdus[0][0]
    pcount = int(h.get("PCOUNT", 0))
    ptypes = [str(h.get(f"PTYPE{k}", "")).strip().upper() for k in range(1, pcount + 1)]
    gcount = int(h["GCOUNT"])
    bitpix = int(h["BITPIX"])
    if bitpix not in (-32, -64):
        raise NeedsCasa(f"BITPIX {bitpix}")
    n_cube = int(np.prod([a.length for a in axes]))
    raw = np.memmap(path, dtype=_FITS_DTYPES[bitpix], mode="r", offset=hdus[0][1],
                    shape=(gcount, pcount + n_cube))
    return _Groups(h, ptypes, raw)


@dataclass(frozen=True)
class _RowParameters:
    """What the group parameters give per row."""

    uvw: np.ndarray                     # (n_row, 3) metres
    time_s: np.ndarray                  # UTC seconds, MJD scale
    ant1_num: np.ndarray                # antenna numbers (AIPS NOSTA) of the baseline
    ant2_num: np.ndarray
    inttim: Optional[np.ndarray]        # integration time (s), if the file has INTTIM


def _row_parameters(groups: _Groups) -> _RowParameters:
    for needed in ("UU", "VV", "WW", "BASELINE", "DATE"):
        if not groups.find(needed):
            raise NeedsCasa(f"no {needed} parameter ({groups.ptypes})")
    for optional in ("SOURCE", "FREQSEL"):
        for k in groups.find(optional):
            if np.unique(groups.raw[:, k]).size > 1:
                raise NeedsCasa(f"several {optional} values")
    uvw = np.stack([groups.par(groups.find(a)[0]) for a in ("UU", "VV", "WW")], axis=1) * C_LIGHT
    jd = sum(groups.par(k) for k in groups.find("DATE"))
    baseline = groups.par(groups.find("BASELINE")[0])
    whole = np.floor(baseline + 1e-3)
    if np.any(np.abs(baseline - whole) > 1e-3):
        raise NeedsCasa("sub-arrays in BASELINE")
    inttim = groups.par(groups.find("INTTIM")[0]) if groups.find("INTTIM") else None
    return _RowParameters(uvw, (jd - 2400000.5) * 86400.0, (whole // 256).astype(np.int64),
                          (whole % 256).astype(np.int64), inttim)


# ---------------------------------------------------------------- the tables

def _antennas(path: str, tables, rows: _RowParameters) -> Tuple[ArrayLayout, np.ndarray,
                                                                   np.ndarray]:
    """The stations of the AIPS AN table and each row's ANTENNA1/ANTENNA2 (table rows)."""
    an_h, an_off = tables["AIPS AN"]
    timsys = str(an_h.get("TIMSYS", an_h.get("TIMESYS", "UTC"))).strip().upper()
    if timsys not in ("UTC", ""):
        raise NeedsCasa(f"time system {timsys}")
    an = _read_bintable(path, an_h, an_off)
    anname = [s.decode("ascii", "replace").split("\0")[0].strip() for s in an["ANNAME"]]
    nosta = np.asarray(an["NOSTA"], np.int64)
    positions = np.asarray(an["STABXYZ"], np.float64).reshape(-1, 3) + np.array(
        [float(an_h.get(k, 0.0)) for k in ("ARRAYX", "ARRAYY", "ARRAYZ")])
    diameters = (np.asarray(an["DIAMETER"], np.float64) if "DIAMETER" in an
                 else np.zeros(len(anname)))
    ant1_num, ant2_num = rows.ant1_num, rows.ant2_num
    lookup = np.full(max(int(nosta.max()), int(ant1_num.max()), int(ant2_num.max())) + 1, -1)
    lookup[nosta] = np.arange(nosta.size)
    ant1, ant2 = lookup[ant1_num], lookup[ant2_num]
    if np.any(ant1 < 0) or np.any(ant2 < 0):
        missing = sorted(set(ant1_num[ant1 < 0].tolist()) | set(ant2_num[ant2 < 0].tolist()))
        raise InputError(f"UVFITS '{path}' has visibilities of antenna number(s) {missing} "
                         "that its antenna table (AIPS AN) does not list; the file is "
                         "inconsistent: write it again with its AN table")
    return ArrayLayout(anname, anname, positions, diameters), ant1, ant2


def _frequency(path: str, axes: List[_Axis], tables) -> Tuple[float, float]:
    """(channel frequency, bandwidth) in Hz: the FREQ axis, moved by AIPS FQ's IF FREQ."""
    freq_axis = _axis(axes, "FREQ")
    if freq_axis is None:
        raise NeedsCasa("no FREQ axis")
    freq = freq_axis.value(1)
    bandwidth = abs(freq_axis.cdelt)
    if "AIPS FQ" in tables:
        fq = _read_bintable(path, *tables["AIPS FQ"])
        if "IF FREQ" in fq:
            freq += float(np.ravel(fq["IF FREQ"])[0])
        for key in ("TOTAL BANDWIDTH", "CH WIDTH"):
            if key in fq and float(np.ravel(fq[key])[0]) > 0:
                bandwidth = abs(float(np.ravel(fq[key])[0]))
                break
    return float(freq), float(bandwidth)


def _field(path: str, h: Dict, axes: List[_Axis], tables) -> Field:
    """The source: the AIPS SU table (one row), else OBJECT and OBSRA/OBSDEC, else RA/DEC axes."""
    src_name = str(h.get("OBJECT", "")).strip() or "SOURCE"
    ra_deg = h.get("OBSRA")
    dec_deg = h.get("OBSDEC")
    if "AIPS SU" in tables:
        su = _read_bintable(path, *tables["AIPS SU"])
        if len(su.get("SOURCE", [])) > 1:
            raise NeedsCasa("several sources")
        if len(su.get("SOURCE", [])) == 1:
            src_name = su["SOURCE"][0].decode("ascii", "replace").strip() or src_name
            ra_deg, dec_deg = float(su["RAEPO"][0]), float(su["DECEPO"][0])
    if ra_deg is None or dec_deg is None:
        ra_ax, dec_ax = _axis(axes, "RA"), _axis(axes, "DEC")
        if ra_ax is None or dec_ax is None:
            raise NeedsCasa("no source position")
        ra_deg, dec_deg = ra_ax.crval, dec_ax.crval
    return Field(src_name, np.radians(float(ra_deg)), np.radians(float(dec_deg)))


def _visibilities(groups: _Groups, axes: List[_Axis], corr: List[str], rows: _RowParameters,
                  ant1: np.ndarray, ant2: np.ndarray) -> Tuple[List[str], Dict[str, np.ndarray]]:
    """(correlations in the set's order, main-table columns) from the group arrays."""
    h, gcount, pcount = groups.header, groups.raw.shape[0], groups.pcount
    names = [a.name for a in axes]
    # reorder the cube to (row, stokes, complex) whatever the axis order
    shape = [a.length for a in axes][::-1]
    cube = groups.raw[:, pcount:].reshape([gcount] + shape)
    if "STOKES" not in names:
        raise NeedsCasa("no STOKES axis")
    order = [names[::-1].index("STOKES") + 1, names[::-1].index("COMPLEX") + 1]
    cube = np.moveaxis(cube, order, [-2, -1]).reshape(gcount, len(corr), 3).astype(np.float32)
    scale, zero = float(h.get("BSCALE", 1.0)), float(h.get("BZERO", 0.0))
    if scale != 1.0 or zero != 0.0:
        cube = cube * scale + zero
    # correlations in the Measurement Set's usual order (RR, RL, LR, LL), as CASA writes them
    by_code = sorted(range(len(corr)), key=lambda k: CORR_CODES[corr[k]])
    corr = [corr[k] for k in by_code]
    cube = cube[:, by_code, :]
    weight = cube[:, :, 2]
    data = (cube[:, :, 0] + 1j * cube[:, :, 1]).astype(np.complex64)
    flag = ~(weight > 0) | ~np.isfinite(data)
    weight_abs = np.where(np.isnan(weight), 0.0, np.abs(weight))   # inf stays, as CASA keeps it
    with np.errstate(divide="ignore"):
        sigma = np.where(weight_abs > 0, 1.0 / np.sqrt(weight_abs), 0.0)
    inttim = rows.inttim
    return corr, {"TIME": rows.time_s, "ANTENNA1": ant1, "ANTENNA2": ant2, "UVW": rows.uvw,
                  "DATA": data, "FLAG": flag, "WEIGHT": weight_abs.astype(np.float32),
                  "SIGMA": sigma.astype(np.float32),
                  **({"INTERVAL": inttim, "EXPOSURE": inttim} if inttim is not None else {})}


# ---------------------------------------------------------------- the reader

def read_uvfits_direct(path: str, hdus) -> UvfitsContents:
    """Everything create_ms needs from a plain UVFITS file; NeedsCasa for anything else.

    ``hdus``: the file's (header, data offset, data bytes), as
    :func:`hitops.io.fits.read_headers` gives them (checked by
    :func:`hitops.io.detect.check_uvfits`: the AIPS AN table is there).
    """
    h = hdus[0][0]
    axes = _axes(h)
    corr = _correlations(axes)
    groups = _groups(path, hdus, axes)
    rows = _row_parameters(groups)
    tables = {str(t.get("EXTNAME", "")).strip(): (t, off) for t, off, _ in hdus[1:]}
    layout, ant1, ant2 = _antennas(path, tables, rows)
    freq, bandwidth = _frequency(path, axes, tables)
    field = _field(path, h, axes, tables)
    corr, main = _visibilities(groups, axes, corr, rows, ant1, ant2)
    telescope = str(h.get("TELESCOP", "VLBA")).strip()
    return UvfitsContents(
        layout, Band(freq, bandwidth, tuple(corr)), field, main,
        telescope if telescope.upper() in _CASA_TELESCOPES else "VLBA",
        _read_bintable(path, *tables["AIPS NX"]) if "AIPS NX" in tables else None)


def _scan_from_nx(nx: Optional[Dict], n_row: int) -> np.ndarray:
    """SCAN_NUMBER per row from an AIPS NX table's START VIS / END VIS (1 when absent)."""
    scan = np.ones(n_row, np.int32)
    if not nx or "START VIS" not in nx or "END VIS" not in nx:
        return scan
    for k, (a, b) in enumerate(zip(np.ravel(nx["START VIS"]), np.ravel(nx["END VIS"])), start=1):
        scan[max(int(a) - 1, 0):min(int(b), n_row)] = k
    return scan


def import_uvfits_direct(path: str, hdus, out: str) -> None:
    """Write the Measurement Set ``out`` from a plain UVFITS file (hitops.io.ms_create)."""
    contents = read_uvfits_direct(path, hdus)
    main = {**contents.main,
            "SCAN_NUMBER": _scan_from_nx(contents.nx, contents.main["TIME"].size)}
    create_ms(out, contents.layout, contents.band, contents.field, main,
              telescope=contents.telescope, overwrite=True)
