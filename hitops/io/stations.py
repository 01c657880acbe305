"""Station identity of a Measurement Set: the codes every log line, report and table uses.

A station is known by ANTENNA::NAME, except where NAME is empty or a bare
number: CASA ``importuvfits`` names the antennas '1', '2', ... and keeps the
station codes (AA, AP, ...) in ANTENNA::STATION, and two bands imported that way
number their stations differently as soon as one band has a station the other
lacks.  Stations are therefore paired across bands by these codes, never by
antenna index, and checked against their positions where both tables have them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from ..errors import StationError
from .metadata import Antennas, read_antennas

#: paired stations farther apart than this are not the same station (JCMT and SMA,
#: 160 m apart on Maunakea, are; KVN Yonsei and Pyeongchang, ~20 km, are not)
SAME_STATION_M = 1000.0


@dataclass
class Stations:
    """The stations of one band, in ANTENNA-table order."""

    ms: str
    codes: List[str]                  # what HITOPS calls each station
    positions: Optional[np.ndarray]   # (n_ant, 3) ITRF metres; None when not on the Earth
    column: str                       # "NAME" or "STATION": where the codes came from

    @property
    def n_ant(self) -> int:
        return len(self.codes)


def _is_placeholder(name: str) -> bool:
    return not name.strip() or name.strip().isdigit()


def read_stations(ms: str, role: str = "Measurement Set") -> Stations:
    """Station codes (NAME, or STATION where NAME is empty or a number) and positions."""
    return stations_of(ms, read_antennas(ms), role)


def stations_of(ms: str, antennas: Antennas, role: str = "Measurement Set") -> Stations:
    """:func:`read_stations` of antennas already read (a run's :class:`SetMetadata`)."""
    n_ant = antennas.n_ant
    names = [n.strip() for n in antennas.names]
    stations = [s.strip() for s in antennas.stations]
    positions = antennas.positions
    if n_ant == 0:
        raise StationError(f"{role} '{ms}' has an empty ANTENNA table; the set has no stations")
    column = "NAME"
    codes = names
    if any(_is_placeholder(n) for n in names):
        if all(not _is_placeholder(s) for s in stations):
            codes, column = stations, "STATION"
        else:
            bad = [i for i, (n, s) in enumerate(zip(names, stations))
                   if _is_placeholder(n) and _is_placeholder(s)]
            raise StationError(
                f"{role} '{ms}': antenna(s) {', '.join(map(str, bad))} have no usable station "
                f"name (ANTENNA::NAME {[names[i] for i in bad]}, ANTENNA::STATION "
                f"{[stations[i] for i in bad]}); station codes are needed to pair the bands: "
                "set ANTENNA::NAME to the codes (e.g. with python-casacore putcell)")
    duplicates = sorted({c for c in codes if codes.count(c) > 1})
    if duplicates:
        raise StationError(
            f"{role} '{ms}': station code(s) {', '.join(duplicates)} appear more than once in "
            f"ANTENNA::{column}; the bands cannot be paired by station: give each station its "
            "own code")
    if positions is not None:
        radius = np.linalg.norm(positions, axis=1)
        # placeholder positions (zeros, as some converters write) say nothing about identity
        if not np.all(radius > 1e3):
            positions = None
    return Stations(ms=ms, codes=codes, positions=positions, column=column)
