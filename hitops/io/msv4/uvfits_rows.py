"""What the UVFITS export reads of a processing set: one data group as MSv2 rows and the setup.

The second backend of hitops/io/uvfits_ms.py (issue 37): the same :class:`MainRows`
and :class:`Setup`, so :func:`hitops.io.uvfits.export_uvfits` writes a data group of
an MSv4 processing set exactly as it writes the MSv2 column the group came from.

* a "column" names a data group as calibrate's do (hitops/io/msv4/columns.py: DATA ->
  ``base``, PWC_DATA -> ``pwc``); the group's own correlated data, flag, weight and
  UVW are read (a result group's flags are its own, e.g. FLAG_PWC: the MSv2 FLAG after
  the same run);
* rows: every partition's present cells (:class:`~hitops.io.msv4.rows.PartitionReader`),
  sorted by time, then baseline (ANTENNA1, ANTENNA2), then data description, as the
  writer's random groups are; ANTENNA1/2 index the set's merged antennas;
* MSv4 keeps a weight per channel: it is given as the weight spectrum (xradio spreads an
  MSv2's WEIGHT over the channels, so the values are the v2 writer's);
  WEIGHT (per row) is its channel mean, as hitops/io/msv4/columns.py defines it;
* INTERVAL (the file's INTTIM) is each cell's EFFECTIVE_INTEGRATION_TIME (the MSv2's
  EXPOSURE, equal to INTERVAL in the sets CASA importuvfits and hitops write), else the
  partition's ``integration_time``; FLAG_ROW is all False (xradio folds it into the flags);
* the setup: windows, field and stations from :func:`hitops.io.metadata.read_metadata`
  (hitops/io/msv4/layout.py), TELESCOP from the antenna dataset's
  ``overall_telescope_name`` and OBSERVER from the partition's ``observation_info``
  (where xradio puts OBSERVATION::TELESCOPE_NAME and OBSERVER).

The store is only read.
"""

from __future__ import annotations

from dataclasses import replace
from typing import List, Tuple

import numpy as np

from ...errors import MeasurementSetError
from ..uvfits_ms import MainRows, Setup, setup_of
from .columns import group_of_column, require_columns
from .layout import ProcessingSetLayout, read_layout
from .rows import PartitionReader, PartitionRows
from .store import open_store, quiet_zarr, zarr_group

#: the MSv2 columns the writer reads, in the order uvfits_ms.read_main gives them
_ROW_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "DATA_DESC_ID", "FIELD_ID")


def read_group_rows(ps: str, column: str, role: str) -> MainRows:
    """The data group ``column`` names, every partition's rows, as :class:`MainRows`."""
    store = open_store(ps, role)
    require_columns(store, [column], role, "name a data group the store holds "
                                           "(DATA is 'base', PWC_DATA is 'pwc')")
    layout = read_layout(store)
    group = group_of_column(column)
    parts = [_partition_rows(layout, p.name, group) for p in layout.partitions]
    rows = [r for r, _ in parts]
    if sum(r.n_row for r in rows) == 0:
        raise MeasurementSetError(f"{role} '{ps}' has no rows to export")
    interval = np.concatenate([seconds for _, seconds in parts])
    cols = {name: np.concatenate([getattr(r, name.lower()) for r in rows])
            for name in _ROW_COLUMNS}
    order = np.lexsort((cols["DATA_DESC_ID"], cols["ANTENNA2"], cols["ANTENNA1"], cols["TIME"]))
    weight_spectrum = np.concatenate([r.weight for r in rows])[order]
    cols = {name: values[order] for name, values in cols.items()}
    cols["UVW"] = np.concatenate([r.uvw for r in rows])[order]
    cols["INTERVAL"] = interval[order]
    cols["FLAG"] = np.concatenate([r.flag for r in rows])[order]
    cols["FLAG_ROW"] = np.zeros(order.size, bool)
    cols["WEIGHT"] = weight_spectrum.mean(axis=1)
    vis = np.concatenate([r.data for r in rows])[order]
    return MainRows(cols, vis, weight_spectrum)


def _partition_rows(layout: ProcessingSetLayout, partition: str,
                    group: str) -> Tuple[PartitionRows, np.ndarray]:
    """(every row of the partition's ``group``, each row's integration time in seconds)."""
    reader = PartitionReader(layout, partition, group)
    variables: List[str] = ["DATA", "FLAG", "UVW"]
    if reader.group.weight:
        variables.append("WEIGHT")
    rows = reader.read((0, reader.n_time), variables)
    if rows.weight is None:
        # a group without weights: every sample counts once (the MSv2's default WEIGHT)
        rows = replace(rows, weight=np.ones(rows.data.shape, np.float32))
    return rows, _integration_times(reader, rows)


def _integration_times(reader: PartitionReader, rows: PartitionRows) -> np.ndarray:
    """INTTIM of each row: EFFECTIVE_INTEGRATION_TIME of its cell (xradio's name for the
    MSv2's EXPOSURE, which CASA importuvfits and hitops write equal to INTERVAL: the EHT's
    averaged rows have 4.4-10 s each), else the partition's one ``integration_time``."""
    name = "EFFECTIVE_INTEGRATION_TIME"
    if name not in reader.entry.arrays:
        return np.full(rows.n_row, reader.integration_time)
    with quiet_zarr():
        grid = np.asarray(zarr_group(reader.layout.store.path)[reader.entry.name][name][...],
                          np.float64)
    seconds = grid[rows.time_index, rows.baseline]
    return np.where(np.isfinite(seconds), seconds, reader.integration_time)


def read_group_setup(ps: str, main: MainRows, role: str) -> Setup:
    """The windows (as IFs), correlations, field and stations of the processing set."""
    from ..metadata import read_metadata

    meta = read_metadata(ps)
    fields = np.unique(main.cols["FIELD_ID"])
    if fields.size > 1:
        names = ", ".join(meta.fields.names[int(f)] for f in fields)
        raise MeasurementSetError(
            f"{role} '{ps}' holds {fields.size} fields {fields.tolist()}; UVFITS export takes "
            f"one ({names}): split the Measurement Set v2 it came from by field (CASA split "
            "field=...) and convert each part")
    telescope, observer = observation_of(ps)
    return setup_of(meta, main, role, telescope or "VLBA", observer or "hitops")


def observation_of(ps: str) -> Tuple[str, str]:
    """(telescope, observer) as xradio keeps OBSERVATION's TELESCOPE_NAME and OBSERVER:
    the first partition's antenna dataset and observation_info; '' where absent."""
    store = open_store(ps)
    with quiet_zarr():
        partition = zarr_group(store.path)[store.partitions[0].name]
        info = partition.attrs.get("observation_info") or {}
        telescope = str(partition["antenna_xds"].attrs.get("overall_telescope_name") or "")
    observer = info.get("observer", "")
    if isinstance(observer, (list, tuple)):
        observer = observer[0] if observer else ""
    return telescope, str(observer)
