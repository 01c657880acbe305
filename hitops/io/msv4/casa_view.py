"""A processing set's subtables as an empty Measurement Set v2, for CASA's calibration tables.

CASA lays a calibration table out from a Measurement Set (``calibrater.createcaltable``
copies its ANTENNA, FIELD, SPECTRAL_WINDOW and OBSERVATION subtables: hitops/io/caltable.py),
and CASA reads Measurement Sets v2 only.  So ``hitops calibrate --caltable`` on a processing
set (issue 37) hands CASA :func:`casa_view`: a Measurement Set of no rows in a temporary
directory whose subtables say what the processing set's metadata says
(:func:`hitops.io.metadata.read_metadata`, hitops/io/msv4/layout.py), laid out by
:func:`hitops.io.ms_create.create_ms` as hitops's own sets are:

* ANTENNA: the merged stations in ANTENNA id order (NAME, STATION, POSITION,
  DISH_DIAMETER, MOUNT);
* SPECTRAL_WINDOW: every window in SPECTRAL_WINDOW_ID order, its channels (CHAN_FREQ,
  CHAN_WIDTH; EFFECTIVE_BW and RESOLUTION the width's size), REF_FREQUENCY,
  TOTAL_BANDWIDTH and NAME (xradio's window name without its ``_<id>``);
* FIELD: every field (NAME, PHASE_DIR as DELAY_DIR and REFERENCE_DIR too), TIME the
  set's first time; POLARIZATION and DATA_DESCRIPTION as the layout recovered them;
* OBSERVATION: TELESCOPE_NAME, OBSERVER, PROJECT and RELEASE_DATE from the partition's
  ``observation_info`` and ``antenna_xds`` (where xradio keeps them), TIME_RANGE the
  set's first and last time.

The table CASA then writes refers to the processing set (its MSName keyword is set to the
store's path) and applies to the Measurement Set v2 the store was converted from: the
subtables agree (tests/test_msv4_export.py compares them column by column).  The store
is only read; the view is removed when the ``with`` block ends.
"""

from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Tuple

import numpy as np

from .. import tables
from ..metadata import SetMetadata, read_metadata
from ..ms_create import CORR_NAMES, ArrayLayout, Band, Field, create_ms
from .layout import read_layout, split_id
from .rows import PartitionReader
from .store import open_store, quiet_zarr, zarr_group
from .uvfits_rows import observation_of

#: casacore's MEpoch origin (MJD 0) for RELEASE_DATE
_MJD_EPOCH = np.datetime64("1858-11-17T00:00:00", "us")


@contextmanager
def casa_view(ps: str) -> Iterator[str]:
    """The path of an empty Measurement Set v2 holding the processing set's subtables."""
    meta = read_metadata(ps)
    directory = tempfile.mkdtemp(prefix="hitops-casa-view-")
    try:
        ms = str(Path(directory) / (Path(ps).name.replace(".zarr", "") + ".ms"))
        _write_view(ps, meta, ms)
        yield ms
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def _write_view(ps: str, meta: SetMetadata, ms: str) -> None:
    ant = meta.antennas
    corr_names = tuple(CORR_NAMES[c] for c in meta.polarizations[0].corr_types)
    window = meta.windows[0]
    telescope, observer = observation_of(ps)
    create_ms(ms, ArrayLayout(ant.names, ant.stations, ant.positions, ant.dish_diameters),
              Band(float(window.chan_freq[0]), float(abs(window.chan_width[0])), corr_names),
              Field(meta.fields.names[0], *(float(x) for x in meta.fields.phase_dirs[0])),
              {"TIME": np.zeros(0), "ANTENNA1": np.zeros(0, np.int32),
               "ANTENNA2": np.zeros(0, np.int32), "UVW": np.zeros((0, 3)),
               "DATA": np.zeros((0, len(corr_names)), np.complex64)},
              telescope=telescope or "VLBA")
    first, last = _time_range(ps)
    with tables.subtable(ms, "ANTENNA", writable=True) as t:
        if ant.mounts is not None:
            t.putcol("MOUNT", [m or "alt-az" for m in ant.mounts])
    _windows(ms, ps, meta)
    _fields(ms, meta, first)
    _setups(ms, meta)
    with tables.subtable(ms, "OBSERVATION", writable=True) as t:
        t.putcol("TIME_RANGE", np.array([[first, last]]))
        t.putcell("OBSERVER", 0, observer or "hitops")
        project, release = _project_and_release(ps)
        t.putcell("PROJECT", 0, project)
        t.putcell("RELEASE_DATE", 0, last if release is None else release)


def _windows(ms: str, ps: str, meta: SetMetadata) -> None:
    names = [split_id(w.v4_name)[0] for w in read_layout(open_store(ps)).windows]
    with tables.subtable(ms, "SPECTRAL_WINDOW", writable=True) as t:
        t.addrows(len(meta.windows) - 1)
        for row, (window, name) in enumerate(zip(meta.windows, names)):
            width = np.asarray(window.chan_width, np.float64)
            for column, value in (("NUM_CHAN", int(window.chan_freq.size)),
                                  ("CHAN_FREQ", np.asarray(window.chan_freq, np.float64)),
                                  ("CHAN_WIDTH", width), ("EFFECTIVE_BW", np.abs(width)),
                                  ("RESOLUTION", np.abs(width)),
                                  ("REF_FREQUENCY", float(window.ref_frequency)),
                                  ("TOTAL_BANDWIDTH", float(window.total_bandwidth)),
                                  ("NET_SIDEBAND", int(window.net_sideband)),
                                  ("MEAS_FREQ_REF", 5), ("NAME", name), ("FREQ_GROUP", 0),
                                  ("FREQ_GROUP_NAME", "Group 1"), ("IF_CONV_CHAIN", 0),
                                  ("FLAG_ROW", False)):
                t.putcell(column, row, value)


def _fields(ms: str, meta: SetMetadata, first: float) -> None:
    fields = meta.fields
    with tables.subtable(ms, "FIELD", writable=True) as t:
        t.addrows(len(fields.names) - 1)
        for row, (name, direction) in enumerate(zip(fields.names, fields.phase_dirs)):
            cell = np.asarray(direction, np.float64).reshape(1, 2)
            for column, value in (("NAME", name), ("CODE", ""), ("TIME", first),
                                  ("NUM_POLY", 0), ("DELAY_DIR", cell), ("PHASE_DIR", cell),
                                  ("REFERENCE_DIR", cell), ("SOURCE_ID", row),
                                  ("FLAG_ROW", False)):
                t.putcell(column, row, value)


def _setups(ms: str, meta: SetMetadata) -> None:
    """POLARIZATION and DATA_DESCRIPTION rows beyond create_ms's first, as recovered."""
    with tables.subtable(ms, "POLARIZATION", writable=True) as t:
        t.addrows(len(meta.polarizations) - 1)
        for row, setup in enumerate(meta.polarizations):
            t.putcell("NUM_CORR", row, len(setup.corr_types))
            t.putcell("CORR_TYPE", row, np.array(setup.corr_types, np.int32))
            t.putcell("CORR_PRODUCT", row, np.array(setup.receptors, np.int32))
            t.putcell("FLAG_ROW", row, False)
    with tables.subtable(ms, "DATA_DESCRIPTION", writable=True) as t:
        t.addrows(len(meta.data_descriptions) - 1)
        for row, dd in enumerate(meta.data_descriptions):
            t.putcell("SPECTRAL_WINDOW_ID", row, int(dd.window))
            t.putcell("POLARIZATION_ID", row, int(dd.polarization))
            t.putcell("FLAG_ROW", row, False)


def _time_range(ps: str) -> Tuple[float, float]:
    """(first, last) TIME (MSv2 seconds) over every partition's time coordinate."""
    layout = read_layout(open_store(ps))
    times = [PartitionReader(layout, p.name).times for p in layout.partitions]
    return (float(min(t.min() for t in times if t.size)),
            float(max(t.max() for t in times if t.size)))


def _project_and_release(ps: str):
    """(PROJECT, RELEASE_DATE in MJD seconds or None) of the first partition's
    observation_info (xradio writes project_UID and an ISO release_date)."""
    store = open_store(ps)
    with quiet_zarr():
        info = zarr_group(store.path)[store.partitions[0].name].attrs.get(
            "observation_info") or {}
    release = info.get("release_date")
    try:
        seconds = float((np.datetime64(str(release), "us") - _MJD_EPOCH)
                        / np.timedelta64(1, "us")) * 1e-6 if release else None
    except ValueError:
        seconds = None
    return str(info.get("project_UID") or ""), seconds
