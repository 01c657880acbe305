"""FITS with numpy: headers read, cards and binary tables written.

A FITS file is a sequence of HDUs, each a header of 80-character cards in
2880-byte blocks followed by its big-endian data padded to whole blocks (FITS
Standard 4.0, sections 3-4 and 7.3).  hitops reads UVFITS and FITS-IDI headers
(:mod:`hitops.io.detect`, :mod:`hitops.io.uvfits_read`) and writes UVFITS
(:mod:`hitops.io.uvfits`) with these few functions, so the package needs no
FITS library; the tests read the files back with astropy, CASA and eht-imaging.
The time keywords of an array table (GSTIA0, IATUTC, RDATE), which UVFITS's AIPS
AN and FITS-IDI's ARRAY_GEOMETRY share, are computed here too.
"""

from __future__ import annotations

import math
import os
from typing import Dict, List, Sequence, Tuple

import numpy as np

#: bytes in a FITS block (headers and data are padded to whole blocks)
BLOCK = 2880
#: TAI - UTC (s) from each date on (the leap seconds of the mm-VLBI era)
LEAP_SECONDS = [(51179.0, 32.0), (53736.0, 33.0), (54832.0, 34.0), (56109.0, 35.0),
                (57204.0, 36.0), (57754.0, 37.0)]


# ---------------------------------------------------------------- headers (read)

def _parse_value(text: str):
    text = text.strip()
    if text.startswith("'"):
        end = text.find("'", 1)
        while end != -1 and text[end + 1:end + 2] == "'":   # '' is an escaped quote
            end = text.find("'", end + 2)
        return text[1:end if end != -1 else None].replace("''", "'").rstrip()
    value = text.split("/")[0].strip()
    if value in ("T", "F"):
        return value == "T"
    try:
        return int(value)
    except ValueError:
        pass
    try:
        return float(value.replace("D", "E"))
    except ValueError:
        return value


def read_headers(path) -> List[Tuple[Dict, int, int]]:
    """Every HDU of a FITS file as (header dict, data offset, data bytes); data not read.

    Raises :class:`ValueError` naming the problem when the file is not FITS or
    a header is cut off; a data block that ends past the end of the file is
    left for the caller to report (its offset and size are returned).
    """
    size = os.path.getsize(path)
    out = []
    offset = 0
    with open(path, "rb") as fh:
        while offset < size:
            header: Dict = {}
            start = offset
            ended = False
            while not ended:
                fh.seek(offset)
                block = fh.read(BLOCK)
                if len(block) < BLOCK:
                    if out and not block.strip(b"\0 "):
                        return out      # padding or zeros after the last HDU
                    raise ValueError(f"header at byte {start} is cut off at byte {size}")
                offset += BLOCK
                for i in range(0, BLOCK, 80):
                    card = block[i:i + 80].decode("ascii", errors="replace")
                    key = card[:8].strip()
                    if key == "END":
                        ended = True
                        break
                    if card[8:10] == "= " and key and key not in header:
                        header[key] = _parse_value(card[10:])
            if not out and not header.get("SIMPLE"):
                raise ValueError("it does not start with a FITS primary header (SIMPLE = T)")
            if out and "XTENSION" not in header:
                if not header:
                    return out
                raise ValueError(f"bytes after the data at {start} are not a FITS extension")
            n_data = data_bytes(header)
            out.append((header, offset, n_data))
            offset += -(-n_data // BLOCK) * BLOCK
    return out


def data_bytes(header: Dict) -> int:
    """Size of an HDU's data in bytes (without padding), from its header."""
    naxis = int(header.get("NAXIS", 0))
    if naxis == 0:
        return 0
    dims = [int(header.get(f"NAXIS{k}", 0)) for k in range(1, naxis + 1)]
    if header.get("GROUPS") and dims[0] == 0:
        dims = dims[1:]
    n = int(np.prod(dims)) if dims else 0
    bits = abs(int(header.get("BITPIX", 8)))
    return bits // 8 * int(header.get("GCOUNT", 1)) * (int(header.get("PCOUNT", 0)) + n)


# ---------------------------------------------------------------- write

def card(key: str, value=None, comment: str = "") -> str:
    """One 80-character header card (HISTORY and COMMENT cards take free text)."""
    if key in ("HISTORY", "COMMENT", ""):
        return f"{key:<8}{str(value or '')}"[:80].ljust(80)
    if isinstance(value, bool):
        text = f"{'T' if value else 'F':>20}"
    elif isinstance(value, (int, np.integer)):
        text = f"{int(value):>20d}"
    elif isinstance(value, (float, np.floating)):
        text = f"{float(value):>20.13G}" if math.isfinite(float(value)) else f"{0.0:>20.13G}"
        if "E" not in text and "." not in text:
            text = f"{float(value):>20.1f}"
    else:
        s = str(value).replace("'", "''")
        text = f"'{s:<8}'"
    line = f"{key:<8}= {text}"
    if comment:
        line = f"{line} / {comment}"
    return line[:80].ljust(80)


def header_bytes(cards: Sequence[str]) -> bytes:
    """The cards, END and the blank padding to a whole block."""
    text = "".join(cards) + "END".ljust(80)
    text += " " * (-len(text) % BLOCK)
    return text.encode("ascii")


def pad(n: int) -> bytes:
    """The zero bytes that fill ``n`` bytes of data to a whole block."""
    return b"\0" * (-n % BLOCK)


def bintable(name: str, columns: Sequence[Tuple[str, str, str, np.ndarray]],
             keywords: Sequence[Tuple[str, object]], n_row: int) -> bytes:
    """A binary table HDU: columns (TTYPE, TFORM, TUNIT, values), rows big-endian."""
    fields = []
    for ttype, tform, _unit, values in columns:
        count = int(tform[:-1]) if tform[:-1] else 1
        code = tform[-1]
        if count == 0:
            continue
        dtype = {"A": f"S{count}", "J": ">i4", "E": ">f4", "D": ">f8", "I": ">i2",
                 "L": "S1"}[code]
        shape = () if code == "A" or count == 1 else (count,)
        fields.append((ttype, dtype, shape))
    rows = np.zeros(n_row, dtype=[(f, d, s) for f, d, s in fields])
    for ttype, tform, _unit, values in columns:
        if tform.startswith("0"):
            continue
        if tform.endswith("A"):
            rows[ttype] = [str(v).encode("ascii", "replace") for v in values]
        else:
            rows[ttype] = np.asarray(values).reshape(rows[ttype].shape)
    cards = [card("XTENSION", "BINTABLE"), card("BITPIX", 8), card("NAXIS", 2),
             card("NAXIS1", rows.dtype.itemsize), card("NAXIS2", n_row),
             card("PCOUNT", 0), card("GCOUNT", 1), card("TFIELDS", len(columns))]
    for k, (ttype, tform, unit, _values) in enumerate(columns, start=1):
        cards.append(card(f"TTYPE{k}", ttype))
        cards.append(card(f"TFORM{k}", tform))
        if unit:
            cards.append(card(f"TUNIT{k}", unit))
    cards.append(card("EXTNAME", name))
    cards.append(card("EXTVER", 1))
    cards += [card(k, v) for k, v in keywords]
    data = rows.tobytes()
    return header_bytes(cards) + data + pad(len(data))


# ---------------------------------------------------------------- array tables' time keywords

def gst0_deg(jd0: float) -> float:
    """Greenwich mean sidereal time at 0h UT of the Julian day jd0 (IAU 1982), degrees."""
    t = (jd0 - 2451545.0) / 36525.0
    seconds = 24110.54841 + 8640184.812866 * t + 0.093104 * t * t - 6.2e-6 * t ** 3
    return (seconds / 240.0) % 360.0


def tai_minus_utc(mjd: float) -> float:
    """IATUTC: TAI - UTC in seconds on the day ``mjd`` (32 s before 1999)."""
    value = 32.0
    for start, leap in LEAP_SECONDS:
        if mjd >= start:
            value = leap
    return value


def iso_date(jd0: float) -> str:
    """RDATE / DATE-OBS: the calendar date (YYYY-MM-DD) of the Julian day at 0h ``jd0``."""
    mjd = int(round(jd0 - 2400000.5))
    # days from 1858-11-17 (MJD 0)
    import datetime

    return (datetime.date(1858, 11, 17) + datetime.timedelta(days=mjd)).isoformat()
