"""A Measurement Set's metadata, read once per set per run: :class:`SetMetadata`.

Antennas (NAME, STATION, POSITION, DISH_DIAMETER, MOUNT), fields (NAME, PHASE_DIR),
spectral windows (CHAN_FREQ, CHAN_WIDTH, REF_FREQUENCY, NUM_CHAN, TOTAL_BANDWIDTH,
NET_SIDEBAND), data descriptions (-> window
and polarization) and polarizations (CORR_TYPE, and CORR_PRODUCT: the receptor
of ANTENNA1 and of ANTENNA2 of each correlation), in one pass: one open per
subtable.  A run calls :func:`read_metadata` once per set and passes the frozen
result down (hitops/calibrate/plan.py: ``build_plan``); nothing is cached here.

The backend seam: :func:`read_metadata` is what a caller asks for a set's
metadata, whatever the set's format.  The MSv2 reader (:func:`_read_msv2`, through
hitops/io/tables.py) reads a casacore table; an MSv4 processing set (a zarr store:
hitops/io/msv4/, docs/msv4.md) is read by :func:`_read_msv4` from its
``antenna_xds``, ``field_and_source_xds``, the ``frequency`` and ``polarization``
coordinates (hitops/io/msv4/layout.py) into the same :class:`SetMetadata`, chosen by
what the path holds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from ..errors import MeasurementSetError
from . import tables
from .msv4.layout import read_layout
from .msv4.store import is_zarr_store, open_store


@dataclass(frozen=True, eq=False)
class Antennas:
    """The ANTENNA table in row order (positions None when the table has no POSITION)."""

    names: Tuple[str, ...]              # ANTENNA::NAME, as stored
    stations: Tuple[str, ...]           # ANTENNA::STATION ('' per row when absent)
    positions: Optional[np.ndarray]     # (n_ant, 3) ITRF metres, float64
    dish_diameters: Optional[np.ndarray] = None   # DISH_DIAMETER (m); None when absent
    mounts: Optional[Tuple[str, ...]] = None      # MOUNT ('alt-az', ...); None when absent

    @property
    def n_ant(self) -> int:
        return len(self.names)


@dataclass(frozen=True, eq=False)
class Fields:
    """The FIELD table in row order."""

    names: Tuple[str, ...]
    phase_dirs: np.ndarray              # (n_field, 2) (RA, Dec) radians: PHASE_DIR's first term


@dataclass(frozen=True, eq=False)
class Window:
    """One SPECTRAL_WINDOW row (NUM_CHAN kept apart from CHAN_FREQ: a damaged table may
    disagree, and the callers say so)."""

    chan_freq: np.ndarray               # (n_chan,) Hz, float64, as stored
    chan_width: np.ndarray              # (n_chan,) Hz, float64, as stored (may be negative)
    ref_frequency: float                # Hz
    num_chan: int
    total_bandwidth: float = 0.0        # Hz
    net_sideband: int = 1               # NET_SIDEBAND (1 upper) ; 1 when absent


@dataclass(frozen=True)
class DataDescription:
    """One DATA_DESCRIPTION row: the window and polarization setup of its rows."""

    window: int                         # SPECTRAL_WINDOW_ID
    polarization: int                   # POLARIZATION_ID


@dataclass(frozen=True)
class Polarization:
    """One POLARIZATION row."""

    corr_types: Tuple[int, ...]                 # casacore Stokes codes (5 RR ... 12 YY)
    receptors: Tuple[Tuple[int, int], ...]      # CORR_PRODUCT: (ANTENNA1's, ANTENNA2's) receptor


@dataclass(frozen=True, eq=False)
class SetMetadata:
    """What hitops reads of a set's subtables, read once (:func:`read_metadata`)."""

    ms: str
    antennas: Antennas
    fields: Fields
    #: indexed by SPECTRAL_WINDOW_ID, DATA_DESC_ID and POLARIZATION_ID as the rows are
    windows: Tuple[Window, ...]
    data_descriptions: Tuple[DataDescription, ...]
    polarizations: Tuple[Polarization, ...]

    def has_groups(self) -> bool:
        """True when rows may mix fields or data descriptions (more than one row of either)."""
        return len(self.data_descriptions) > 1 or len(self.fields.names) > 1

    def window_of(self, ddid: int) -> int:
        """SPECTRAL_WINDOW_ID of data description ``ddid``."""
        return self._description(ddid).window

    def corr_types_of(self, ddid: int) -> Tuple[int, ...]:
        """CORR_TYPE of the polarization setup of data description ``ddid``."""
        return self.polarizations[self._description(ddid).polarization].corr_types

    def _description(self, ddid: int) -> DataDescription:
        if not 0 <= ddid < len(self.data_descriptions):
            raise MeasurementSetError(
                f"'{self.ms}': rows refer to DATA_DESC_ID {ddid}, which the DATA_DESCRIPTION "
                f"table ({len(self.data_descriptions)} rows) does not hold; the set is damaged")
        return self.data_descriptions[ddid]


def read_metadata(ms: str) -> SetMetadata:
    """The :class:`SetMetadata` of the set at ``ms`` (one open per subtable).

    The one entry for every backend: a zarr store is read as an MSv4 processing set
    (a foreign, half-written or other-schema store is one ProcessingSetError line),
    anything else as a Measurement Set v2.
    """
    path = str(ms).rstrip("/")
    return _read_msv4(path) if is_zarr_store(path) else _read_msv2(path)


def _read_msv4(path: str) -> SetMetadata:
    """A processing set's metadata, ids recovered as hitops/io/msv4/layout.py says."""
    layout = read_layout(open_store(path))
    ant = layout.antennas
    return SetMetadata(
        ms=path,
        antennas=Antennas(names=ant.names, stations=ant.stations, positions=ant.positions,
                          dish_diameters=ant.dish_diameters, mounts=ant.mounts),
        fields=Fields(names=layout.fields.names, phase_dirs=layout.fields.phase_dirs),
        # MSv4 keeps one channel width per window, no TOTAL_BANDWIDTH and no NET_SIDEBAND
        windows=tuple(Window(chan_freq=w.chan_freq, chan_width=w.chan_width,
                             ref_frequency=w.ref_frequency, num_chan=w.chan_freq.size,
                             total_bandwidth=float(np.sum(np.abs(w.chan_width))))
                      for w in layout.windows),
        data_descriptions=tuple(DataDescription(window=w, polarization=p)
                                for w, p in layout.data_descriptions),
        polarizations=tuple(Polarization(corr_types=c.corr_types, receptors=c.receptors)
                            for c in layout.polarizations))


def _read_msv2(ms: str) -> SetMetadata:
    return SetMetadata(ms=ms, antennas=read_antennas(ms), fields=_fields(ms), windows=_windows(ms),
                       data_descriptions=_data_descriptions(ms),
                       polarizations=_polarizations(ms))


def read_antennas(ms: str) -> Antennas:
    """The ANTENNA table alone (one open), for a reader that needs only the stations."""
    with tables.subtable(ms, "ANTENNA") as t:
        n_ant, present = t.nrows(), set(t.colnames())
        names = tuple(str(n) for n in t.getcol("NAME")) if n_ant else ()
        stations = (tuple(str(s) for s in t.getcol("STATION"))
                    if n_ant and "STATION" in present else ("",) * n_ant)
        positions = (np.asarray(t.getcol("POSITION"), dtype=np.float64)
                     if n_ant and "POSITION" in present else None)
        diameters = t.getcol("DISH_DIAMETER") if n_ant and "DISH_DIAMETER" in present else None
        mounts = (tuple(str(m) for m in t.getcol("MOUNT"))
                  if n_ant and "MOUNT" in present else None)
    return Antennas(names=names, stations=stations, positions=positions,
                    dish_diameters=diameters, mounts=mounts)


def _fields(ms: str) -> Fields:
    with tables.subtable(ms, "FIELD") as t:
        n_field = t.nrows()
        names = tuple(str(n) for n in t.getcol("NAME")) if n_field else ()
        # PHASE_DIR is (NUM_POLY + 1, 2) per row; its first term is the direction at TIME
        dirs = [_array_cell(t, "PHASE_DIR", i, np.float64, np.full(2, np.nan)).reshape(-1, 2)[0]
                for i in range(n_field)]
    return Fields(names=names, phase_dirs=np.array(dirs, np.float64).reshape(-1, 2))


def _windows(ms: str) -> Tuple[Window, ...]:
    with tables.subtable(ms, "SPECTRAL_WINDOW") as t:
        sideband = "NET_SIDEBAND" in t.colnames()
        return tuple(Window(chan_freq=_array_cell(t, "CHAN_FREQ", i, np.float64),
                            chan_width=_array_cell(t, "CHAN_WIDTH", i, np.float64),
                            ref_frequency=float(t.getcell("REF_FREQUENCY", i)),
                            num_chan=int(t.getcell("NUM_CHAN", i)),
                            total_bandwidth=float(t.getcell("TOTAL_BANDWIDTH", i)),
                            net_sideband=int(t.getcell("NET_SIDEBAND", i)) if sideband else 1)
                     for i in range(t.nrows()))


def _data_descriptions(ms: str) -> Tuple[DataDescription, ...]:
    with tables.subtable(ms, "DATA_DESCRIPTION") as t:
        if not t.nrows():
            return ()
        spw, pol = t.getcol("SPECTRAL_WINDOW_ID"), t.getcol("POLARIZATION_ID")
    return tuple(DataDescription(int(w), int(p)) for w, p in zip(spw, pol))


def _polarizations(ms: str) -> Tuple[Polarization, ...]:
    with tables.subtable(ms, "POLARIZATION") as t:
        return tuple(
            Polarization(corr_types=tuple(int(c) for c in _array_cell(t, "CORR_TYPE", i, int)),
                         receptors=tuple((int(a), int(b)) for a, b in
                                         _array_cell(t, "CORR_PRODUCT", i, int).reshape(-1, 2)))
            for i in range(t.nrows()))


def _array_cell(t, column: str, row: int, dtype, empty=None) -> np.ndarray:
    """An array cell as ``dtype``; ``empty`` (default: no values) where the row holds no array
    (a row added without it: the callers name what is missing where they need it)."""
    if column in t.colnames() and t.iscelldefined(column, row):
        return np.asarray(t.getcell(column, row), dtype)
    return np.asarray(np.array([], dtype) if empty is None else empty, dtype)
