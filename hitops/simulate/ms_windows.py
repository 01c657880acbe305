"""Write a band's Measurement Set: one channel (hitops.io.ms_create) or several windows.

A wideband band gets one SPECTRAL_WINDOW row and one DATA_DESCRIPTION row per window
(window w -> DATA_DESC_ID w -> SPECTRAL_WINDOW_ID w), all sharing one POLARIZATION
row, and DATA/FLAG of fixed shape (n_chan, n_corr) (every window of a band has the
same channel count).  SPECTRAL_WINDOW follows CASA's conventions: CHAN_FREQ is each
channel's centre, REF_FREQUENCY the first channel's frequency, TOTAL_BANDWIDTH
n_chan x CHAN_WIDTH.  SIGMA is the noise of one channel (the MS definition: "rms noise
for channel with unity bandpass response") and WEIGHT = 1 / SIGMA^2.

The one-channel, one-window case is written by :func:`hitops.io.ms_create.create_ms`
unchanged, so the single-channel scenes' sets are what they were.  The subtables
other than SPECTRAL_WINDOW and DATA_DESCRIPTION are filled by ms_create's own
``_fill_subtables`` (one definition of what CASA and WSClean need).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Iterator, Mapping, Optional

import numpy as np

from ..io.atomic import replaced_directory
from ..io.ms_create import ArrayLayout, Band, Field, _CONSTANT_SCALARS, _fill_subtables, create_ms
from .scene_parts import BandSpec
from ..io import tables

#: rows per tile of the array columns (~1 MB tiles for 64 channels x 2 correlations)
_TILE_BYTES = 1 << 20


def write_band_ms(path: Path, layout: ArrayLayout, band: BandSpec, corr_types, field: Field,
                  blocks: Iterator[Mapping[str, np.ndarray]], n_row: int, time_range: tuple,
                  telescope: str, calibrator: Optional[Field] = None) -> Path:
    """The band's Measurement Set at ``path`` (replaced: the caller owns the name).

    ``blocks`` yields the main-table columns block after block in row order
    (:func:`hitops.simulate.bands.band_blocks`), ``n_row`` rows in all; a one-channel
    band comes as one block.  ``time_range`` (first, last TIME) fills the subtables.
    ``calibrator``: a second FIELD row (FIELD_ID 1; the blocks then carry FIELD_ID).
    """
    if not band.is_wideband:
        create_ms(path, layout, Band(band.freq_hz, band.bandwidth_hz, tuple(corr_types)),
                  field, next(iter(blocks)), telescope=telescope, overwrite=True)
    else:
        _create_wideband(Path(path), layout, band, tuple(corr_types), field, blocks, n_row,
                         time_range, telescope)
    if calibrator is not None:
        _add_field(path, calibrator)
    return path


def _add_field(path: Path, field: Field) -> None:
    """FIELD row 1: the calibrator, its directions in the layout of row 0."""
    with tables.subtable(path, "FIELD", writable=True) as t:
        t.addrows(1)
        direction = np.array([[field.ra_rad, field.dec_rad]])
        for name in ("DELAY_DIR", "PHASE_DIR", "REFERENCE_DIR"):
            t.putcell(name, 1, direction)
        t.putcell("NAME", 1, field.name)
        for name in ("CODE", "TIME", "NUM_POLY", "SOURCE_ID", "FLAG_ROW"):
            t.putcell(name, 1, t.getcell(name, 0))


def _table_desc(n_chan: int, n_corr: int, model: bool):
    extra = ([tables.array_column("MODEL_DATA", 0j, [n_chan, n_corr], "complex",
                                  "The model data")] if model else [])
    return tables.table_description(extra + [
        tables.array_column("DATA", 0j, [n_chan, n_corr], "complex", "The data column"),
        tables.array_column("FLAG", False, [n_chan, n_corr], "boolean", "The data flags"),
        tables.array_column("SIGMA", 0.0, [n_corr], "float",
                            "Estimated rms noise for channel with unity bandpass response"),
        tables.array_column("WEIGHT", 0.0, [n_corr], "float",
                            "Weight for each polarization spectrum"),
    ])


def _dminfo(n_chan: int, n_corr: int, model: bool) -> dict:
    """Array columns tiled by whole rows; scalars as hitops.io.ms_create lays them out."""
    info = {}
    arrays = ((("DATA", [n_corr, n_chan], 8), ("FLAG", [n_corr, n_chan], 1),
               ("SIGMA", [n_corr], 4), ("WEIGHT", [n_corr], 4), ("UVW", [3], 8))
              + ((("MODEL_DATA", [n_corr, n_chan], 8),) if model else ()))
    for name, cell, size in arrays:
        rows = max(64, _TILE_BYTES // (int(np.prod(cell)) * size))
        info[f"tiled_{name}"] = {"TYPE": "TiledColumnStMan", "NAME": f"Tiled{name}",
                                 "SPEC": {"DEFAULTTILESHAPE": cell + [rows]}, "COLUMNS": [name]}
    info["ism"] = {"TYPE": "IncrementalStMan", "NAME": "ISMConstants", "SPEC": {},
                   "COLUMNS": [c for c in _CONSTANT_SCALARS if c != "DATA_DESC_ID"]}
    return info


def _main_columns(columns: Mapping[str, np.ndarray], n_chan: int, n_corr: int) -> dict:
    time = np.asarray(columns["TIME"], np.float64)
    n_row = time.size
    interval = np.asarray(columns["INTERVAL"], np.float64)
    out = {
        "TIME": time, "TIME_CENTROID": time, "INTERVAL": interval, "EXPOSURE": interval,
        "ANTENNA1": np.asarray(columns["ANTENNA1"], np.int32),
        "ANTENNA2": np.asarray(columns["ANTENNA2"], np.int32),
        "UVW": np.asarray(columns["UVW"], np.float64),
        "DATA": np.asarray(columns["DATA"], np.complex64).reshape(n_row, n_chan, n_corr),
        "FLAG": np.zeros((n_row, n_chan, n_corr), bool),
        "SIGMA": np.asarray(columns["SIGMA"], np.float32),
        "WEIGHT": np.asarray(columns["WEIGHT"], np.float32),
        "SCAN_NUMBER": np.asarray(columns["SCAN_NUMBER"], np.int32),
        "DATA_DESC_ID": np.asarray(columns["DATA_DESC_ID"], np.int32),
    }
    if "MODEL_DATA" in columns:
        out["MODEL_DATA"] = np.asarray(columns["MODEL_DATA"],
                                       np.complex64).reshape(n_row, n_chan, n_corr)
    if "FIELD_ID" in columns:
        out["FIELD_ID"] = np.asarray(columns["FIELD_ID"], np.int32)
    for name in _CONSTANT_SCALARS:
        if name not in out:
            out[name] = np.zeros(n_row, bool if name == "FLAG_ROW" else np.int32)
    return out


def _create_wideband(path: Path, layout: ArrayLayout, band: BandSpec, corr_types,
                     field: Field, blocks, n_row: int, time_range: tuple, telescope: str) -> Path:
    n_chan, n_corr = band.n_chan, len(corr_types)
    # the first block says whether the scene writes a model column (a resolved calibrator)
    first = next(iter(blocks))
    blocks = itertools.chain([first], blocks)
    model = "MODEL_DATA" in first
    with replaced_directory(path) as partial:
        ms = tables.new_measurement_set(str(partial), _table_desc(n_chan, n_corr, model),
                                        _dminfo(n_chan, n_corr, model))
        ms.addrows(n_row)
        start = 0
        for block in blocks:
            main = _main_columns(block, n_chan, n_corr)
            size = main["TIME"].size
            for name, value in main.items():
                ms.putcol(name, value, startrow=start, nrow=size)
            start += size
        ms.close()
        if start != n_row:
            raise RuntimeError(f"wrote {start} of {n_row} rows of {path}")
        _fill_subtables(str(partial), layout, Band(band.freq_hz, band.bandwidth_hz, corr_types),
                        field, time_range, telescope)
        _fill_windows(str(partial), band)
    return path


def _fill_windows(ms: str, band: BandSpec) -> None:
    """SPECTRAL_WINDOW and DATA_DESCRIPTION: one row per window (replacing the one row
    ms_create wrote)."""
    chan_freq = band.chan_freq()
    n_win, n_chan = chan_freq.shape
    width = band.channel_width_hz
    with tables.subtable(ms, "SPECTRAL_WINDOW", writable=True) as t:
        t.addrows(n_win - t.nrows())
        for w in range(n_win):
            t.putcell("NUM_CHAN", w, n_chan)
            t.putcell("CHAN_FREQ", w, chan_freq[w])
            for col in ("CHAN_WIDTH", "EFFECTIVE_BW", "RESOLUTION"):
                t.putcell(col, w, np.full(n_chan, width))
            t.putcell("REF_FREQUENCY", w, float(chan_freq[w, 0]))
            t.putcell("TOTAL_BANDWIDTH", w, n_chan * width)
            t.putcell("MEAS_FREQ_REF", w, 5)  # TOPO
            t.putcell("NAME", w, f"{band.name}-w{w}-{band.centres_hz[w] / 1e9:g}GHz")
            t.putcell("NET_SIDEBAND", w, 1)
            t.putcell("FREQ_GROUP", w, 0)
            t.putcell("FREQ_GROUP_NAME", w, "Group 1")
            t.putcell("IF_CONV_CHAIN", w, 0)
            t.putcell("FLAG_ROW", w, False)
    with tables.subtable(ms, "DATA_DESCRIPTION", writable=True) as t:
        t.addrows(n_win - t.nrows())
        t.putcol("SPECTRAL_WINDOW_ID", np.arange(n_win, dtype=np.int32))
        t.putcol("POLARIZATION_ID", np.zeros(n_win, np.int32))
        t.putcol("FLAG_ROW", np.zeros(n_win, bool))
