"""Make the FITS headers WSClean writes conform to the FITS fixed format.

WSClean 3.1 writes real header values with 15 significant digits, so a
negative small number such as ``CDELT1  = -1.38888888888889E-09`` runs to
column 31, one past the end of the fixed-format value field (columns 11-30,
FITS 4.0 section 4.2.4).  CASA reads the file but logs "FITS card 26: CDELT1
... Numeric value does not conform to FITS fixed format" every time it opens
it (32 lines in one demo run).  :func:`conform_header` rewrites such cards in
place with the same value in 20 characters (14 significant digits: a relative
change below 1e-14), right-justified, keeping the comment; nothing else in the
file changes, and a header that already conforms is not touched (so the file's
modification time, which Stimela's freshness checks read, stays as it is).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import List

CARD = 80
BLOCK = 2880
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([ED][+-]?\d+)?$", re.IGNORECASE)


def _fixed(value: str) -> str | None:
    """``value`` rewritten to fit 20 characters, or None if it cannot be."""
    number = float(value.upper().replace("D", "E"))
    for digits in range(15, 5, -1):
        text = f"{number:.{digits}G}"
        if "E" not in text and "." not in text:
            text += "."
        if len(text) <= 20:
            return text
    return None


def _conform_card(card: str) -> str | None:
    """The card rewritten, or None when it already conforms or is not a numeric value."""
    if card[8:10] != "= " or card.startswith(("COMMENT", "HISTORY", "CONTINUE")):
        return None
    field = card[10:]
    value, sep, comment = field.partition("/")
    text = value.strip()
    if not text or text.startswith("'") or not _NUMBER.match(text):
        return None
    # fixed format: the value ends in column 30 (index 29) and nothing but blanks before
    end = len(value.rstrip()) + 10
    if end == 30 and len(text) <= 20:
        return None
    fixed = _fixed(text)
    if fixed is None:
        return None
    new = f"{card[:10]}{fixed:>20}"
    if sep:
        new += " / " + comment.strip()
    return new[:CARD].ljust(CARD)


def conform_header(path: str | Path) -> List[str]:
    """Rewrite the non-conforming numeric cards of the primary header of ``path`` in place.

    Returns the keywords rewritten (empty: the file was not touched).  Files
    that are not FITS (CASA images are directories) are left alone.
    """
    path = Path(path)
    if not path.is_file():
        return []
    with open(path, "rb") as fh:
        head = fh.read(BLOCK)
        if not head.startswith(b"SIMPLE  ="):
            return []
        header = bytearray(head)
        while b"END" + b" " * 77 not in [bytes(header[i:i + CARD])
                                        for i in range(0, len(header), CARD)]:
            more = fh.read(BLOCK)
            if len(more) < BLOCK:
                return []  # truncated: not ours to repair
            header += more
    changed = []
    for i in range(0, len(header), CARD):
        card = header[i:i + CARD].decode("ascii", errors="replace")
        if card.startswith("END "):
            break
        new = _conform_card(card)
        if new is not None:
            header[i:i + CARD] = new.encode("ascii")
            changed.append(card[:8].strip())
    if changed:
        with open(path, "r+b") as fh:
            fh.write(header)
    return changed
