"""What an input file is, and whether it can be converted: checked before CASA sees it.

``hitops calibrate`` takes a Measurement Set, a UVFITS file or a FITS-IDI file
for each band.  :func:`detect_format` tells them apart from the file itself (a
directory is a Measurement Set; a FITS file with random groups is UVFITS; a
FITS file with ``NAXIS = 0`` is FITS-IDI).  :func:`check_uvfits` and
:func:`check_fitsidi` then read the headers only (one line naming the file and
the remedy, :class:`hitops.errors.InputError`): not FITS, truncated, no antenna
table, several frequency setups (FQ rows), IFs its FQ table does not describe (several
IFs are imported as several windows).  CASA can abort the whole
process on some malformed files, so these checks come before any conversion
(:mod:`hitops.io.convert`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict

from ..errors import InputError
from .fits import BLOCK, read_headers


# ---------------------------------------------------------------- format detection

def _cards(block: bytes) -> Dict[str, str]:
    """Keyword -> raw value text of the 80-character cards in a header block."""
    out = {}
    for i in range(0, len(block) - 79, 80):
        card = block[i:i + 80].decode("ascii", errors="replace")
        key = card[:8].strip()
        if card[8:10] == "= " and key and key not in out:
            out[key] = card[10:].split("/")[0].strip().strip("'").strip()
    return out


def detect_format(path, role: str = "input") -> str:
    """'ms', 'uvfits' or 'fitsidi'; raise naming the file when it is none of them.

    A path that does not exist or is a directory counts as 'ms': the Measurement
    Set checks that follow say what is wrong with it.
    """
    p = Path(path)
    if not p.is_file():
        return "ms"
    with open(p, "rb") as fh:
        head = fh.read(BLOCK)
    if not head.startswith(b"SIMPLE  ="):
        raise InputError(f"{role} '{path}' is neither a Measurement Set (a directory) nor a "
                         "FITS file (UVFITS or FITS-IDI); check the path")
    cards = _cards(head)
    if cards.get("GROUPS") == "T" and cards.get("NAXIS1") == "0" and int(cards.get("GCOUNT", "0") or 0) > 0:
        return "uvfits"
    if cards.get("NAXIS") == "0":
        return "fitsidi"
    raise InputError(f"{role} '{path}' is a FITS file but neither UVFITS (random groups) nor "
                     "FITS-IDI (UV_DATA tables); hitops calibrate reads visibilities only")


# ---------------------------------------------------------------- checks before CASA

@dataclass(frozen=True)
class FileSummary:
    """What the checks learnt of a file that can be converted."""

    rows: int                       # visibilities: UVFITS groups, FITS-IDI UV_DATA rows
    n_antenna: int                  # rows of the antenna table

def hdus_of(path: str, role: str):
    """Headers of every HDU with their data offsets and sizes (data not read)."""
    size = os.path.getsize(path)
    try:
        out = read_headers(path)
    except (OSError, ValueError) as err:
        raise InputError(f"{role} '{path}' cannot be read as FITS ({err}); the file is "
                         "damaged or truncated: copy it again from its source") from err
    for header, start, n_bytes in out:
        # the data must be in the file; the last block's padding may be missing
        if start + n_bytes > size:
            raise InputError(
                f"{role} '{path}' is truncated: {size} bytes, but its "
                f"{header.get('EXTNAME', 'primary')} data end at byte {start + n_bytes}; copy "
                "the file again from its source")
    return out


def check_uvfits(path, role: str = "UVFITS input") -> FileSummary:
    """Check a UVFITS file before it is imported; return a summary. One-line errors."""
    hdus = hdus_of(str(path), role)
    primary = hdus[0][0]
    naxis = int(primary.get("NAXIS", 0))
    axes = {str(primary.get(f"CTYPE{k}", "")).strip(): int(primary.get(f"NAXIS{k}", 0))
            for k in range(2, naxis + 1)}
    if not primary.get("GROUPS") or "COMPLEX" not in axes:
        raise InputError(f"{role} '{path}' is not UVFITS: no random-group visibilities "
                         "(GROUPS = T, a COMPLEX axis); give a UVFITS file")
    tables = {str(h.get("EXTNAME", "")).strip(): h for h, _, _ in hdus[1:]}
    if "AIPS AN" not in tables:
        raise InputError(
            f"{role} '{path}' has no antenna table (AIPS AN); the stations are unknown and "
            "cannot be paired with the other band: write the file with its AN table (AIPS "
            "FITTP, CASA exportuvfits, eht-imaging save_uvfits)")
    # several IFs go in as several spectral windows (CASA importuvfits), paired with the
    # other band's windows by hitops calibrate; the FQ table must describe them all
    n_if = axes.get("IF", 1)
    fq = tables.get("AIPS FQ")
    if fq is not None and int(fq.get("NO_IF", n_if)) != n_if:
        raise InputError(
            f"{role} '{path}' holds {n_if} IFs on its IF axis but its AIPS FQ table describes "
            f"{int(fq['NO_IF'])}; the file is inconsistent: write it again (AIPS FITTP, CASA "
            "exportuvfits, eht-imaging save_uvfits)")
    if fq is not None and int(fq.get("NAXIS2", 1)) > 1:
        raise InputError(
            f"{role} '{path}' holds {int(fq['NAXIS2'])} frequency setups (rows of its AIPS FQ "
            "table); hitops calibrate takes one per band: split the file by FREQID first "
            "(AIPS SPLIT, or CASA importuvfits + split spw=...)")
    if int(primary.get("GCOUNT", 0)) == 0:
        raise InputError(f"{role} '{path}' holds no visibilities (GCOUNT = 0)")
    return FileSummary(rows=int(primary["GCOUNT"]),
                       n_antenna=int(tables["AIPS AN"].get("NAXIS2", 0)))


def check_fitsidi(path, role: str = "FITS-IDI input") -> FileSummary:
    """Check a FITS-IDI file before it is imported; return a summary. One-line errors."""
    hdus = hdus_of(str(path), role)
    tables = {}
    for h, _, _ in hdus[1:]:
        tables.setdefault(str(h.get("EXTNAME", "")).strip(), []).append(h)
    if "UV_DATA" not in tables:
        raise InputError(f"{role} '{path}' has no UV_DATA table; it holds no visibilities "
                         "(a FITS-IDI file without data, or not FITS-IDI)")
    for name in ("ARRAY_GEOMETRY", "ANTENNA"):
        if name not in tables:
            raise InputError(f"{role} '{path}' has no {name} table; the stations are unknown: "
                             "give the complete correlator output")
    if "FREQUENCY" not in tables:
        raise InputError(f"{role} '{path}' has no FREQUENCY table; the frequency setup is unknown")
    freq_rows = sum(int(h.get("NAXIS2", 0)) for h in tables["FREQUENCY"])
    if freq_rows > 1:
        raise InputError(f"{role} '{path}' holds {freq_rows} frequency setups (FREQUENCY "
                         "rows); give one setup per band (split it after CASA importfitsidi)")
    rows = sum(int(h.get("NAXIS2", 0)) for h in tables["UV_DATA"])
    if rows == 0:
        raise InputError(f"{role} '{path}' holds no visibilities (UV_DATA has no rows)")
    return FileSummary(rows=rows,
                       n_antenna=sum(int(h.get("NAXIS2", 0)) for h in tables["ANTENNA"]))
