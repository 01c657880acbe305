"""Read the columns diagnose needs from a Measurement Set onto a (baseline, time) grid.

The Measurement Set access is the package's shared reader
(:mod:`hitops.io.read`, the one ``hitops calibrate`` uses): dask-ms reads
only the columns asked for (TIME, ANTENNA1, ANTENNA2, FLAG, FLAG_ROW,
SCAN_NUMBER, UVW when a (u,v) plot is wanted, and the compared data columns)
in storage order and large row chunks, in one ``dask.compute``; casacore I/O
is not the bottleneck (GUIDE: ~0.1 s for a 1.2 M-row one-channel column), so
the rows are then laid out in memory with
:func:`hitops.io.layout.baseline_time_layout`.

FLAG_ROW is folded into FLAG; several channels of one window are vector-averaged
over their unflagged channels with a warning; autocorrelations are dropped.  A set
holding several fields or spectral windows is refused here (FIELD_ID / DATA_DESC_ID
are read only when the FIELD / DATA_DESCRIPTION subtables have more than one row):
``hitops diagnose`` reads wideband sets with :mod:`hitops.diagnose.spectral_read`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from ..errors import ColumnError, InputError, MeasurementSetError
from ..io.access import raise_if_damaged, require_subtables
from ..io.metadata import SetMetadata, read_metadata
from ..io.stations import stations_of
from ..io import read as msio
from ..io.layout import baseline_time_layout
from ..io import tables
from ..io.msv4.store import is_zarr_store, open_store

log = logging.getLogger("hitops.diagnose")

#: casacore Stokes codes -> names (casacore/measures/Measures/Stokes.h)
STOKES_NAMES = {1: "I", 2: "Q", 3: "U", 4: "V", 5: "RR", 6: "RL", 7: "LR", 8: "LL",
                9: "XX", 10: "XY", 11: "YX", 12: "YY"}
PARALLEL_HANDS = ("RR", "LL", "XX", "YY", "I")


class BaselineNames:
    """Baseline names of a grid with ``antenna_names``, ``ant1`` and ``ant2``."""

    @property
    def n_bl(self) -> int:
        return int(self.ant1.size)

    def baseline_name(self, b: int) -> str:
        return f"{self.antenna_names[self.ant1[b]]}-{self.antenna_names[self.ant2[b]]}"

    @property
    def baseline_names(self) -> List[str]:
        return [self.baseline_name(b) for b in range(self.n_bl)]


@dataclass
class GridData(BaselineNames):
    """Selected baselines of one Measurement Set on a (baseline, time) grid."""

    ms: str
    antenna_names: List[str]            # station codes by antenna index (hitops.io.stations)
    ant1: np.ndarray                    # (n_bl,) antenna index
    ant2: np.ndarray                    # (n_bl,)
    times: np.ndarray                   # (n_time,) MJD seconds
    scan: np.ndarray                    # (n_bl, n_time) SCAN_NUMBER, -1 where no row
    flag: np.ndarray                    # (n_bl, n_time, n_corr) True = unusable (incl. no row)
    vis: Dict[str, np.ndarray]          # column -> (n_bl, n_time, n_corr) view of vis_stack
    vis_stack: np.ndarray               # (n_bl, n_time, n_col, n_corr) complex, columns in order
    corr_names: List[str]               # names of the selected correlations
    dt: float                           # sampling interval (s)
    freq_hz: float                      # reference frequency of the spectral window
    uvw: Optional[np.ndarray] = None    # (n_bl, n_time, 3) metres, NaN where no row
    warnings: List[str] = field(default_factory=list)

    @property
    def n_time(self) -> int:
        return int(self.times.size)


def check_ms(ms: str) -> None:
    path = Path(ms)
    if is_zarr_store(path):   # an MSv4 processing set: foreign or half-written stores refused
        open_store(ms)
        return
    if not (path / "table.dat").exists():
        raise MeasurementSetError(f"{ms}: not a Measurement Set (no table.dat); check the path")
    require_subtables(ms, "Measurement Set")


def data_columns(ms: str) -> List[str]:
    """Complex visibility-like columns of the main table."""
    with tables.main_table(ms) as tab:
        names = []
        for name in tab.colnames():
            desc = tab.getcoldesc(name)
            if desc.get("valueType") in ("complex", "dcomplex") and desc.get("ndim", 0) in (2, -1):
                names.append(name)
        return names


def select_correlations(corr_types: Sequence[int], wanted: Optional[str], ms: str):
    """Indices and names of the correlations to use.

    ``wanted``: empty/None for the parallel hands (RR, LL or XX, YY; a point
    source has no signal in the cross hands, whose phases are noise),
    ``all``, or a comma-separated list of names.
    """
    names = [STOKES_NAMES.get(int(c), str(c)) for c in corr_types]
    if not wanted:
        idx = [i for i, n in enumerate(names) if n in PARALLEL_HANDS] or list(range(len(names)))
    elif wanted.strip().lower() == "all":
        idx = list(range(len(names)))
    else:
        idx = []
        for item in (w.strip().upper() for w in wanted.split(",") if w.strip()):
            if item not in names:
                raise InputError(f"--correlations: '{item}' is not a correlation of {ms} "
                                 f"(it has {','.join(names)}); pick from those or give 'all'")
            if names.index(item) not in idx:
                idx.append(names.index(item))
        if not idx:
            raise InputError(f"--correlations '{wanted}' selects nothing; give names such as "
                             f"{','.join(names)} or 'all'")
    return idx, [names[i] for i in idx]


def select_baselines(pairs_ant1: np.ndarray, pairs_ant2: np.ndarray, names: List[str],
                     wanted: Optional[str], ms: str) -> np.ndarray:
    """Boolean mask over baselines for ``--baselines``.

    Items are ``A-B`` (either order) or a single station ``A`` (all its
    baselines), comma-separated, by ANTENNA::NAME or antenna index.
    """
    n_bl = pairs_ant1.size
    if not wanted:
        return np.ones(n_bl, bool)

    def ant_index(token: str) -> int:
        if token in names:
            return names.index(token)
        upper = [n.upper() for n in names]
        if token.upper() in upper:
            return upper.index(token.upper())
        if token.isdigit() and int(token) < len(names):
            return int(token)
        raise InputError(f"--baselines: station '{token}' is not in {ms} "
                         f"(stations: {', '.join(names)})")

    mask = np.zeros(n_bl, bool)
    for item in (w.strip() for w in wanted.split(",") if w.strip()):
        parts = item.split("-")
        if len(parts) == 1:
            a = ant_index(parts[0])
            mask |= (pairs_ant1 == a) | (pairs_ant2 == a)
        elif len(parts) == 2:
            a, b = ant_index(parts[0]), ant_index(parts[1])
            hit = ((pairs_ant1 == a) & (pairs_ant2 == b)) | ((pairs_ant1 == b) & (pairs_ant2 == a))
            if not hit.any():
                raise InputError(f"--baselines: baseline {item} has no rows in {ms}")
            mask |= hit
        else:
            raise InputError(f"--baselines: cannot read '{item}'; write A-B or A, "
                             "comma-separated (e.g. AP-PV,KC)")
    if not mask.any():
        raise InputError(f"--baselines '{wanted}' selects no cross-correlation baseline in {ms}")
    return mask


def check_columns(ms: str, columns: Sequence[str]) -> None:
    """``ms`` is a readable Measurement Set holding every complex column of ``columns``."""
    check_ms(ms)
    if is_zarr_store(Path(ms)):
        from ..io.msv4.columns import require_columns
        require_columns(open_store(ms), columns, "input", "check --columns")
        return
    available = data_columns(ms)
    missing = [c for c in columns if c not in available]
    if missing:
        raise ColumnError(f"{ms}: column(s) {', '.join(missing)} not found; complex data "
                          f"columns present: {', '.join(available) or 'none'}")


def sampling_interval(ms: str, times: np.ndarray) -> float:
    """The median step of ``times`` (s); with one time only, the median INTERVAL."""
    if times.size > 1:
        dt = float(np.median(np.diff(times)))
    else:
        with tables.main_table(ms) as tab:   # one time step only: fall back on INTERVAL
            dt = float(np.median(tab.getcol("INTERVAL")))
    if not dt > 0:
        raise MeasurementSetError(f"{ms}: cannot find a positive sampling interval "
                                  "(TIME steps and INTERVAL are zero)")
    return dt


def read_values(ms: str, columns: Sequence[str], row_chunk: int) -> Dict[str, np.ndarray]:
    """``columns`` of every row of ``ms``: a Measurement Set v2 through dask-ms, a
    processing set through hitops/io/msv4/set_columns.py (data columns named as data
    groups; FLAG the union of the compared groups' flags)."""
    if is_zarr_store(Path(ms)):
        from ..io.msv4.set_columns import read_set_columns
        return read_set_columns(ms, columns)
    xds = msio.open_main(ms, columns, chunk_rows=row_chunk)
    # the threaded scheduler passed as a function (inside compute_columns): named or
    # default schedulers make dask look for a distributed client, whose import alone
    # costs ~0.2 s of a run budgeted at a few seconds
    try:
        return msio.compute_columns([(xds, columns, None)])[0]
    except RuntimeError as err:
        # casacore does not always say which file is damaged: find the column that fails
        raise_if_damaged(err, [(ms, columns)])
        raise


def read_values_by_group(ms: str, columns: Sequence[str], row_chunk: int, mixed: bool):
    """``{(FIELD_ID, DATA_DESC_ID): {column: values}}`` of every (field, window) group."""
    if not is_zarr_store(Path(ms)):
        groups = msio.open_groups(ms, columns, row_chunk, mixed=mixed)
        keys = sorted(groups)
        return dict(zip(keys, msio.compute_columns([(groups[k], columns, None)
                                                    for k in keys])))
    values = read_values(ms, list(columns) + ["FIELD_ID", "DATA_DESC_ID"], row_chunk)
    keys = sorted(set(zip(values["FIELD_ID"].tolist(), values["DATA_DESC_ID"].tolist())))
    out = {}
    for field_id, ddid in keys:
        rows = (values["FIELD_ID"] == field_id) & (values["DATA_DESC_ID"] == ddid)
        out[(field_id, ddid)] = {c: values[c][rows] for c in columns}
    return out


def read_grid(ms: str, columns: Sequence[str], *, correlations: Optional[str] = None,
              baselines: Optional[str] = None, want_uvw: bool = False,
              row_chunk: int = 400_000, meta: Optional[SetMetadata] = None) -> GridData:
    """Read ``columns`` of ``ms`` for the selected baselines and correlations."""
    ms = str(ms)
    check_columns(ms, columns)

    # station codes (ANTENNA::STATION where NAME is only a number, as after importuvfits)
    meta = read_metadata(ms) if meta is None else meta   # the caller's, read once
    ant_names = stations_of(ms, meta.antennas).codes

    wanted_cols = ["TIME", "ANTENNA1", "ANTENNA2", "FLAG", "FLAG_ROW", "SCAN_NUMBER"]
    if want_uvw:
        wanted_cols.append("UVW")
    wanted_cols += list(dict.fromkeys(columns))
    selection = ["DATA_DESC_ID", "FIELD_ID"] if meta.has_groups() else []
    values = read_values(ms, wanted_cols + selection, row_chunk)
    if values["TIME"].size == 0:
        raise MeasurementSetError(f"{ms}: the main table has no rows")
    ddid = 0
    if selection:
        groups = sorted(set(zip(values["FIELD_ID"].tolist(), values["DATA_DESC_ID"].tolist())))
        if len(groups) > 1:
            text = ", ".join(f"FIELD_ID={f}/DATA_DESC_ID={d}" for f, d in groups)
            raise MeasurementSetError(f"{ms} holds several fields or spectral windows ({text}); "
                                      "split them (e.g. CASA split by field/spw) and diagnose each")
        ddid = int(groups[0][1])
    corr_types = meta.corr_types_of(ddid)
    freq_hz = meta.windows[meta.window_of(ddid)].ref_frequency
    corr_idx, corr_names = select_correlations(corr_types, correlations, ms)

    time = values["TIME"]
    ant1, ant2 = values["ANTENNA1"], values["ANTENNA2"]
    cross = ant1 != ant2
    if not cross.any():
        raise MeasurementSetError(f"{ms}: no cross-correlation rows (only autocorrelations)")
    n_ant = len(ant_names)
    pair_key = ant1.astype(np.int64) * max(n_ant, 1) + ant2
    pairs = np.unique(pair_key[cross])
    mask = select_baselines(pairs // n_ant, pairs % n_ant, ant_names, baselines, ms)
    keep = cross if mask.all() else cross & np.isin(pair_key, pairs[mask])
    # take every row without a copy when nothing is dropped (the usual case)
    rows = slice(None) if keep.all() else np.flatnonzero(keep)

    layout = baseline_time_layout(time[rows], ant1[rows], ant2[rows],
                                  tolerance=1e-3, source=ms)
    warnings: List[str] = []

    # basic indexing (a view) when the correlations are a contiguous run
    if corr_idx == list(range(corr_idx[0], corr_idx[-1] + 1)):
        corr_sel = slice(corr_idx[0], corr_idx[-1] + 1)
    else:
        corr_sel = corr_idx
    flag = values["FLAG"][rows][..., corr_sel] | values["FLAG_ROW"][rows][:, None, None]
    n_chan = flag.shape[1]
    cols = list(dict.fromkeys(columns))
    # all columns in one (n_bl, n_time, n_col, n_corr) block so the kernel
    # walks the segments once for every column
    stack = np.zeros((layout.n_bl, layout.n_time, len(cols), len(corr_idx)),
                     dtype=np.result_type(*[values[c].dtype for c in cols]))
    if n_chan > 1:
        good = ~flag
        count = good.sum(axis=1)
    for i, col in enumerate(cols):
        data = values[col][rows][..., corr_sel]
        if n_chan > 1:
            data = np.where(count > 0, (data * good).sum(axis=1) / np.maximum(count, 1), 0)
        else:
            data = data[:, 0, :]
        stack[layout.bl_of_row, layout.time_of_row, i, :] = data
    vis = {col: stack[:, :, i, :] for i, col in enumerate(cols)}
    if n_chan > 1:
        msg = (f"{ms} has {n_chan} channels: each sample's phase is taken from the vector "
               "average of its unflagged channels (average in frequency first to control this)")
        warnings.append(msg)
        log.warning("%s", msg)
        flag = flag.all(axis=1)
    else:
        flag = flag[:, 0, :]
    flag_grid = layout.to_grid(flag, True)
    scan_grid = layout.to_grid(values["SCAN_NUMBER"][rows].astype(np.int32), -1)

    dt = sampling_interval(ms, layout.times)

    uvw = None
    if want_uvw:
        uvw = layout.to_grid(values["UVW"][rows].astype(np.float64), np.nan)

    return GridData(ms=ms, antenna_names=ant_names, ant1=layout.ant1, ant2=layout.ant2,
                    times=layout.times, scan=scan_grid, flag=flag_grid, vis=vis,
                    vis_stack=stack,
                    corr_names=corr_names, dt=dt, freq_hz=freq_hz, uvw=uvw,
                    warnings=warnings)
