"""Write a complete single-field, single-spectral-window Measurement Set.

python-casacore lays the table out directly: no casatools.simulator, which
labels TAI times as UTC and has crashed on intercontinental arrays.  The
main table gets fixed-shape DATA/FLAG/SIGMA/WEIGHT columns (one channel per
band, as FPT expects) and every subtable CASA's listobs/fringefit/gaincal and
WSClean need is filled in.  The set is built under a temporary name beside
the target and renamed into place last, so a failure never leaves a
half-written Measurement Set behind.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputError, OutputExistsError
from .atomic import replaced_directory
from . import tables

#: Stokes enumeration of casacore (casacore/measures/Measures/Stokes.h)
CORR_CODES = {"RR": 5, "RL": 6, "LR": 7, "LL": 8, "XX": 9, "XY": 10, "YX": 11, "YY": 12}
CORR_NAMES = {code: name for name, code in CORR_CODES.items()}


@dataclass(frozen=True)
class ArrayLayout:
    """Stations of one band, in ANTENNA-table order."""

    names: Sequence[str]            # e.g. "AP" (ANTENNA::NAME)
    stations: Sequence[str]         # e.g. "APEX" (ANTENNA::STATION)
    positions: np.ndarray           # (n_ant, 3) ITRF metres
    diameters: np.ndarray           # (n_ant,) metres


@dataclass(frozen=True)
class Band:
    """One spectral window of one channel."""

    freq_hz: float
    bandwidth_hz: float
    corr_types: Sequence[str] = ("RR", "LL")


@dataclass(frozen=True)
class Field:
    name: str
    ra_rad: float
    dec_rad: float


def _main_table_desc(n_corr: int, model: bool = False):
    """``model``: a MODEL_DATA column too (CASA's model column, as ft/setjy write it)."""
    extra = ([tables.array_column("MODEL_DATA", 0j, [1, n_corr], "complex", "The model data")]
             if model else [])
    return tables.table_description(extra + [
        tables.array_column("DATA", 0j, [1, n_corr], "complex", "The data column"),
        tables.array_column("FLAG", False, [1, n_corr], "boolean",
                            "The data flags, array of bools with same shape as data"),
        tables.array_column("SIGMA", 0.0, [n_corr], "float",
                            "Estimated rms noise for channel with unity bandpass response"),
        tables.array_column("WEIGHT", 0.0, [n_corr], "float",
                            "Weight for each polarization spectrum"),
    ])


#: scalar main-table columns that are written row by row (one StandardStMan each)
_PER_ROW_SCALARS = ("TIME", "TIME_CENTROID", "ANTENNA1", "ANTENNA2", "INTERVAL", "EXPOSURE",
                    "SCAN_NUMBER")
#: scalar columns that are (almost always) constant: IncrementalStMan stores runs
_CONSTANT_SCALARS = ("ARRAY_ID", "DATA_DESC_ID", "FEED1", "FEED2", "FIELD_ID", "FLAG_ROW",
                     "OBSERVATION_ID", "PROCESSOR_ID", "STATE_ID")


def _main_dminfo(n_corr: int, model: bool = False) -> dict:
    """Storage managers of the main table.

    One StandardStMan for everything (casacore's default) makes ``addrows``
    initialise every column bucket by bucket and each ``putcol`` stride
    through all of them: ~4 s for 1.2 M rows.  Array columns in their own
    TiledColumnStMan (~1 MB tiles of whole rows), per-row scalars in their own
    StandardStMan and constant scalars in an IncrementalStMan bring that to
    ~0.4 s (benchmarks/bench_simulate.py).  CASA and WSClean read any manager.
    """
    info = {}
    arrays = (("DATA", [n_corr, 1]), ("FLAG", [n_corr, 1]), ("SIGMA", [n_corr]),
              ("WEIGHT", [n_corr]), ("UVW", [3])) + ((("MODEL_DATA", [n_corr, 1]),) if model else ())
    for name, cell in arrays:
        rows_per_tile = max(1024, (1 << 20) // (int(np.prod(cell)) * 8))
        info[f"tiled_{name}"] = {"TYPE": "TiledColumnStMan", "NAME": f"Tiled{name}",
                                 "SPEC": {"DEFAULTTILESHAPE": cell + [rows_per_tile]},
                                 "COLUMNS": [name]}
    for name in _PER_ROW_SCALARS:
        info[f"ssm_{name}"] = {"TYPE": "StandardStMan", "NAME": f"SSM_{name}",
                               "SPEC": {"BUCKETSIZE": 1 << 18}, "COLUMNS": [name]}
    info["ism"] = {"TYPE": "IncrementalStMan", "NAME": "ISMConstants", "SPEC": {},
                   "COLUMNS": list(_CONSTANT_SCALARS)}
    return info


def _put_rows(ms: str, subtable: str, n_rows: int, columns: Mapping[str, object]) -> None:
    """Add ``n_rows`` rows to a subtable of ``ms`` and fill ``columns`` (name -> values)."""
    with tables.subtable(ms, subtable, writable=True) as t:
        t.addrows(n_rows)
        for name, values in columns.items():
            t.putcol(name, values)


def _receptors(band: Band) -> list:
    circular = band.corr_types[0] in ("RR", "RL", "LR", "LL")
    return ["R", "L"] if circular else ["X", "Y"]


def _antenna_columns(layout: ArrayLayout) -> dict:
    n_ant = len(layout.names)
    return {"NAME": list(layout.names), "STATION": list(layout.stations),
            "POSITION": np.asarray(layout.positions, dtype=np.float64),
            "OFFSET": np.zeros((n_ant, 3)),
            "DISH_DIAMETER": np.asarray(layout.diameters, dtype=np.float64),
            "MOUNT": ["alt-az"] * n_ant, "TYPE": ["GROUND-BASED"] * n_ant,
            "FLAG_ROW": np.zeros(n_ant, bool)}


def _feed_columns(n_ant: int, receptors: list, time_range: tuple) -> dict:
    return {"ANTENNA_ID": np.arange(n_ant, dtype=np.int32),
            "FEED_ID": np.zeros(n_ant, np.int32),
            "SPECTRAL_WINDOW_ID": np.full(n_ant, -1, np.int32),
            "TIME": np.full(n_ant, time_range[0]),
            "INTERVAL": np.full(n_ant, time_range[1] - time_range[0]),
            "NUM_RECEPTORS": np.full(n_ant, 2, np.int32),
            "BEAM_ID": np.full(n_ant, -1, np.int32),
            "BEAM_OFFSET": np.zeros((n_ant, 2, 2)),
            "POLARIZATION_TYPE": np.array([receptors] * n_ant),
            "POL_RESPONSE": np.tile(np.eye(2, dtype=np.complex64), (n_ant, 1, 1)),
            "POSITION": np.zeros((n_ant, 3)),
            "RECEPTOR_ANGLE": np.zeros((n_ant, 2))}


def _spectral_window_columns(band: Band) -> dict:
    width = np.array([[band.bandwidth_hz]])
    return {"NUM_CHAN": np.array([1], np.int32), "CHAN_FREQ": np.array([[band.freq_hz]]),
            "CHAN_WIDTH": width, "EFFECTIVE_BW": width, "RESOLUTION": width,
            "REF_FREQUENCY": np.array([band.freq_hz]),
            "TOTAL_BANDWIDTH": np.array([band.bandwidth_hz]),
            "MEAS_FREQ_REF": np.array([5], np.int32),  # TOPO
            "NAME": [f"{band.freq_hz / 1e9:g}GHz"], "NET_SIDEBAND": np.array([1], np.int32),
            "FREQ_GROUP": np.array([0], np.int32), "FREQ_GROUP_NAME": ["Group 1"],
            "IF_CONV_CHAIN": np.array([0], np.int32), "FLAG_ROW": np.array([False])}


def _polarization_columns(band: Band, receptors: list) -> dict:
    codes = np.array([[CORR_CODES[c] for c in band.corr_types]], np.int32)
    # python-casacore shows a [2, NUM_CORR] cell as (NUM_CORR, 2): one receptor pair
    # per correlation, e.g. RR LL -> [[0, 0], [1, 1]] (as casatools.simulator writes).
    # (A transposed array here made CASA gaincal see only cross hands and stop with
    # "Insufficient unflagged antennas".)
    products = np.array([[[receptors.index(c[0]), receptors.index(c[1])]
                          for c in band.corr_types]], np.int32)
    return {"NUM_CORR": np.array([len(band.corr_types)], np.int32), "CORR_TYPE": codes,
            "CORR_PRODUCT": products, "FLAG_ROW": np.array([False])}


def _field_columns(field: Field, time_range: tuple) -> dict:
    direction = np.array([[[field.ra_rad, field.dec_rad]]])
    return {"NAME": [field.name], "CODE": [""], "TIME": np.array([time_range[0]]),
            "NUM_POLY": np.array([0], np.int32), "DELAY_DIR": direction,
            "PHASE_DIR": direction, "REFERENCE_DIR": direction,
            "SOURCE_ID": np.array([0], np.int32), "FLAG_ROW": np.array([False])}


def _fill_subtables(ms: str, layout: ArrayLayout, band: Band, field: Field,
                    time_range: tuple, telescope: str) -> None:
    """Every subtable CASA's listobs/fringefit/gaincal and WSClean need, one row each
    (ANTENNA and FEED: one per station)."""
    n_ant = len(layout.names)
    receptors = _receptors(band)
    no = np.array([False])
    _put_rows(ms, "ANTENNA", n_ant, _antenna_columns(layout))
    _put_rows(ms, "FEED", n_ant, _feed_columns(n_ant, receptors, time_range))
    _put_rows(ms, "SPECTRAL_WINDOW", 1, _spectral_window_columns(band))
    _put_rows(ms, "POLARIZATION", 1, _polarization_columns(band, receptors))
    _put_rows(ms, "FIELD", 1, _field_columns(field, time_range))
    _put_rows(ms, "DATA_DESCRIPTION", 1, {"SPECTRAL_WINDOW_ID": np.array([0], np.int32),
                                          "POLARIZATION_ID": np.array([0], np.int32),
                                          "FLAG_ROW": no})
    _put_rows(ms, "OBSERVATION", 1, {
        "TELESCOPE_NAME": [telescope], "TIME_RANGE": np.array([time_range]),
        "OBSERVER": ["hitops"], "PROJECT": ["hitops simulation"],
        "RELEASE_DATE": np.array([time_range[1]]), "SCHEDULE_TYPE": [""], "FLAG_ROW": no})
    _put_rows(ms, "STATE", 1, {
        "OBS_MODE": ["OBSERVE_TARGET#ON_SOURCE"], "CAL": np.array([0.0]),
        "LOAD": np.array([0.0]), "SIG": np.array([True]), "REF": np.array([False]),
        "SUB_SCAN": np.array([0], np.int32), "FLAG_ROW": no})
    _put_rows(ms, "PROCESSOR", 1, {
        "TYPE": ["CORRELATOR"], "SUB_TYPE": ["hitops"], "TYPE_ID": np.array([0], np.int32),
        "MODE_ID": np.array([0], np.int32), "FLAG_ROW": no})


#: main-table columns the caller must supply
REQUIRED_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "UVW", "DATA")


def create_ms(path: str | Path, layout: ArrayLayout, band: Band, field: Field,
              main: Mapping[str, np.ndarray], *, telescope: str = "VLBA",
              overwrite: bool = False) -> Path:
    """Write a Measurement Set at ``path``; return its path.

    ``main`` holds main-table columns by name: TIME (UTC seconds, MJD scale),
    ANTENNA1, ANTENNA2, UVW (n_row, 3) and DATA (n_row, n_corr) or
    (n_row, 1, n_corr) are required; FLAG, SIGMA, WEIGHT, SCAN_NUMBER,
    INTERVAL, EXPOSURE default to unflagged, unit sigma/weight, scan 1 and the
    median time step; MODEL_DATA (shaped as DATA), when given, adds CASA's model
    column.  Any further columns must already exist in the MS description (e.g.
    FLAG_ROW, STATE_ID).

    ``telescope`` must be a name CASA's Observatories table knows: CASA 6.7
    listobs stops with "Telescope EHT is not recognized by CASA" otherwise,
    hence the default "VLBA" (a VLBI array CASA knows; only used by CASA to
    look up an array reference position).
    """
    path = Path(path)
    missing = [c for c in REQUIRED_COLUMNS if c not in main]
    if missing:
        raise InputError(f"create_ms({path}): main-table columns {missing} not supplied")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path} exists; pass overwrite=True (CLI: --overwrite) "
                                "to replace it")

    time = np.asarray(main["TIME"], dtype=np.float64)
    n_row = time.size
    n_corr = len(band.corr_types)
    data = np.asarray(main["DATA"]).reshape(n_row, 1, n_corr).astype(np.complex64, copy=False)
    if n_row:
        diffs = np.diff(np.unique(time))
        default_dt = float(np.median(diffs)) if diffs.size else 1.0
    else:
        default_dt = 1.0
    columns = {
        "TIME": time,
        "TIME_CENTROID": time,
        "ANTENNA1": np.asarray(main["ANTENNA1"], np.int32),
        "ANTENNA2": np.asarray(main["ANTENNA2"], np.int32),
        "UVW": np.asarray(main["UVW"], np.float64).reshape(n_row, 3),
        "DATA": data,
        "FLAG": np.asarray(main.get("FLAG", np.zeros((n_row, 1, n_corr), bool)),
                           bool).reshape(n_row, 1, n_corr),
        "SIGMA": np.asarray(main.get("SIGMA", np.ones((n_row, n_corr))),
                            np.float32).reshape(n_row, n_corr),
        "WEIGHT": np.asarray(main.get("WEIGHT", np.ones((n_row, n_corr))),
                             np.float32).reshape(n_row, n_corr),
        "SCAN_NUMBER": np.asarray(main.get("SCAN_NUMBER", np.ones(n_row)), np.int32),
        "INTERVAL": np.asarray(main.get("INTERVAL", np.full(n_row, default_dt)), np.float64),
    }
    columns["EXPOSURE"] = np.asarray(main.get("EXPOSURE", columns["INTERVAL"]), np.float64)
    model = "MODEL_DATA" in main
    if model:
        columns["MODEL_DATA"] = np.asarray(main["MODEL_DATA"]).reshape(
            n_row, 1, n_corr).astype(np.complex64, copy=False)
    for name in _CONSTANT_SCALARS:
        columns[name] = np.zeros(n_row, bool if name == "FLAG_ROW" else np.int32)
    for name, value in main.items():
        if name not in columns or name in _CONSTANT_SCALARS:
            columns[name] = np.asarray(value)

    with replaced_directory(path) as partial:
        ms = tables.new_measurement_set(str(partial), _main_table_desc(n_corr, model),
                                        _main_dminfo(n_corr, model))
        ms.addrows(n_row)
        for name, value in columns.items():
            ms.putcol(name, value)
        ms.close()
        t0 = float(time.min()) if n_row else 0.0
        t1 = float(time.max()) if n_row else 0.0
        _fill_subtables(str(partial), layout, band, field, (t0, t1), telescope)
    return path
