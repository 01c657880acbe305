"""What the UVFITS export reads of a Measurement Set: the main-table rows and the setup.

The set's data descriptions become the file's IFs (in frequency order), so they
must share the channel count, channel width and correlations; one field.  Used by
:mod:`hitops.io.uvfits`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..errors import ColumnError, MeasurementSetError
from . import tables
from .metadata import SetMetadata, read_metadata
from .stations import stations_of

#: casacore Stokes code -> AIPS STOKES axis value
AIPS_STOKES = {1: 1, 2: 2, 3: 3, 4: 4, 5: -1, 8: -2, 6: -3, 7: -4, 9: -5, 12: -6, 10: -7, 11: -8}


@dataclass(frozen=True)
class MainRows:
    """The main-table columns written out, in storage order."""

    cols: Dict[str, np.ndarray]              # TIME, ANTENNA1, ANTENNA2, UVW, INTERVAL, ...
    vis: np.ndarray                          # the exported column
    weight_spectrum: Optional[np.ndarray]    # None when the set has none

    @property
    def n_row(self) -> int:
        return int(self.cols["TIME"].size)


@dataclass(frozen=True)
class Setup:
    """The subtable entries of the set's spectral windows (the IFs, in frequency order) and field."""

    chan_freq: np.ndarray                    # (n_if, n_chan)
    chan_width: np.ndarray                   # (n_if, n_chan)
    total_bw: np.ndarray                     # (n_if,)
    sideband: np.ndarray                     # (n_if,)
    ddids: List[int]                         # DATA_DESC_ID of each IF
    corr_types: List[int]                    # casacore Stokes codes, in column order
    direction: np.ndarray                    # (ra, dec) radians
    source: str
    positions: np.ndarray                    # (n_ant, 3) ITRF metres
    diameters: np.ndarray
    mounts: List[str]
    codes: List[str]                         # station codes (hitops.io.stations)
    telescope: str
    observer: str

    @property
    def n_ant(self) -> int:
        return len(self.codes)

    @property
    def n_if(self) -> int:
        return len(self.ddids)

    @property
    def n_chan(self) -> int:
        return int(self.chan_freq.shape[1])


def read_main(ms: str, column: str, role: str) -> MainRows:
    with tables.main_table(ms) as t:
        names = t.colnames()
        if column not in names:
            raise ColumnError(f"{role} '{ms}' has no column {column} to export (columns: "
                              f"{', '.join(sorted(names))})")
        if t.nrows() == 0:
            raise MeasurementSetError(f"{role} '{ms}' has no rows to export")
        cols = {c: t.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "UVW", "INTERVAL",
                                         "FLAG", "FLAG_ROW", "WEIGHT", "SCAN_NUMBER",
                                         "DATA_DESC_ID", "FIELD_ID")}
        vis = t.getcol(column)
        weight_spectrum = (t.getcol("WEIGHT_SPECTRUM")
                           if "WEIGHT_SPECTRUM" in names and t.iscelldefined("WEIGHT_SPECTRUM", 0)
                           else None)
    return MainRows(cols, vis, weight_spectrum)


def single_value(values: np.ndarray, what: str, ms: str) -> int:
    unique = np.unique(values)
    if unique.size > 1:
        raise MeasurementSetError(f"'{ms}' holds {unique.size} {what} {unique.tolist()}; UVFITS "
                                  f"export takes one: split the set first (CASA split)")
    return int(unique[0]) if unique.size else 0


def read_windows(meta: SetMetadata, ddids: np.ndarray):
    """(ddids in frequency order, chan_freq, chan_width, total_bw, sideband, pol) of the
    set's data descriptions, which UVFITS writes as IFs: one channel count, width and
    polarisation setup for all of them, or a one-line error."""
    ms = meta.ms
    spws = np.array([meta.window_of(int(d)) for d in ddids], int)
    pols = [meta.data_descriptions[int(d)].polarization for d in ddids]
    corrs = {meta.polarizations[p].corr_types for p in pols}
    windows = [meta.windows[w] for w in spws]
    freq = [w.chan_freq for w in windows]
    width = [w.chan_width for w in windows]
    total = [w.total_bandwidth for w in windows]
    side = [w.net_sideband for w in windows]
    shapes = {f.size for f in freq}
    steps = {round(float(w[0]), 3) for w in width if w.size}
    if len(shapes) > 1 or len(steps) > 1 or len(corrs) > 1:
        raise MeasurementSetError(
            f"'{ms}': its spectral windows {sorted(set(spws.tolist()))} differ in channel count, "
            "channel width or correlations, and UVFITS IFs share them: split the set (CASA "
            "split spw=...) and export each part")
    order = np.argsort([f[0] for f in freq], kind="stable")
    return ([int(ddids[i]) for i in order], np.stack([freq[i] for i in order]),
            np.stack([width[i] for i in order]), np.array([total[i] for i in order]),
            np.array([side[i] for i in order]), int(pols[0]))


def read_setup(ms: str, main: MainRows, role: str) -> Setup:
    """The data descriptions' windows (as IFs) and correlations, the field, the stations."""
    telescope, observer = "VLBA", "hitops"
    with tables.subtable(ms, "OBSERVATION") as t:
        if t.nrows():
            telescope = str(t.getcell("TELESCOPE_NAME", 0)) or telescope
            observer = str(t.getcell("OBSERVER", 0)) or observer
    return setup_of(read_metadata(ms), main, role, telescope, observer)


def setup_of(meta: SetMetadata, main: MainRows, role: str, telescope: str,
             observer: str) -> Setup:
    """The :class:`Setup` of a set's metadata (either backend: hitops/io/msv4/uvfits_rows.py
    reads a processing set's) and the rows' fields and data descriptions."""
    ms = meta.ms
    field_id = single_value(main.cols["FIELD_ID"], "fields", ms)
    ddids, chan_freq, chan_width, total_bw, sideband, pol = read_windows(
        meta, np.unique(main.cols["DATA_DESC_ID"]))
    corr_types = list(meta.polarizations[pol].corr_types)
    direction = meta.fields.phase_dirs[field_id]
    source = meta.fields.names[field_id] or "SOURCE"
    antennas = meta.antennas
    n_ant = antennas.n_ant
    positions = antennas.positions
    diameters = antennas.dish_diameters if antennas.dish_diameters is not None else np.zeros(n_ant)
    mounts = ([m.lower() for m in antennas.mounts] if antennas.mounts is not None
              else ["alt-az"] * n_ant)
    codes = stations_of(ms, antennas, role).codes
    if n_ant > 255:
        raise MeasurementSetError(f"{role} '{ms}' has {n_ant} antennas; the UVFITS BASELINE "
                                  "parameter holds at most 255")
    unknown = [c for c in corr_types if c not in AIPS_STOKES]
    if unknown:
        raise MeasurementSetError(f"{role} '{ms}': correlation types {unknown} have no UVFITS "
                                  "Stokes code")
    return Setup(chan_freq, chan_width, total_bw, sideband, ddids, corr_types, direction,
                  source, positions, diameters, mounts, list(codes), telescope, observer)
