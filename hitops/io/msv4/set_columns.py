"""A whole processing set's rows as MSv2 columns, for the tools that read a set at once.

``hitops diagnose`` reads a Measurement Set's columns whole (TIME, ANTENNA1/2, FLAG,
the compared data columns) and lays them out on a (baseline, time) grid.  On a
processing set, :func:`read_set_columns` gives the same dictionary: every partition's
rows through :class:`~hitops.io.msv4.rows.PartitionReader`, data columns mapped to data
groups as hitops/io/msv4/columns.py maps them (DATA -> ``base``, CORRECTED_DATA ->
``corrected``, PWC_DATA -> ``pwc``).

FLAG is the union of the flags of the data groups asked for: an MSv2 has one FLAG that
every data column shares, and a calibrated column's flags are written into it (the
input's | not calibrated); a processing set keeps each group's flags apart (the
input's FLAG and a result's FLAG_PWC), so a sample counts in a comparison only where
every compared group has it, which is the MSv2's FLAG after the same run.
"""

from __future__ import annotations

from typing import Dict, List, Sequence

import numpy as np

from .columns import group_of_column, is_data_column, require_columns
from .layout import read_layout
from .rows import PartitionReader, PartitionRows
from .store import open_store

#: row columns the readers give (FLAG_ROW: xradio folds it into the flags)
_ROW_FIELDS = {"TIME": "time", "ANTENNA1": "antenna1", "ANTENNA2": "antenna2",
               "SCAN_NUMBER": "scan_number", "FIELD_ID": "field_id",
               "DATA_DESC_ID": "data_desc_id"}


def read_set_columns(ps: str, columns: Sequence[str], role: str = "input") -> Dict[str, np.ndarray]:
    """{column: values of every row of every partition} for MSv2 ``columns``.

    Partitions come in layout order, rows in time then baseline order within each.
    """
    store = open_store(ps, role)
    asked = list(dict.fromkeys(columns))
    data_columns = [c for c in asked if is_data_column(c) and c not in _ROW_FIELDS
                    and c != "FLAG_ROW"]
    require_columns(store, data_columns, role)
    layout = read_layout(store)
    groups = list(dict.fromkeys(group_of_column(c) for c in data_columns)) or ["base"]
    parts: List[Dict[str, np.ndarray]] = []
    for partition in layout.partitions:
        parts.append(_partition_columns(layout, partition.name, asked, data_columns, groups))
    return {name: np.concatenate([p[name] for p in parts]) for name in asked}


def _partition_columns(layout, partition: str, asked, data_columns, groups):
    """One partition's columns: the row columns and UVW from the first group's read, each
    data column from its group, FLAG the union of the groups' flags."""
    out: Dict[str, np.ndarray] = {}
    flag = None
    for i, group in enumerate(groups):
        variables = ["DATA", "FLAG"] + (["UVW"] if i == 0 and "UVW" in asked else [])
        rows = _whole(PartitionReader(layout, partition, group), variables)
        if i == 0:
            out.update({name: getattr(rows, field) for name, field in _ROW_FIELDS.items()
                        if name in asked})
            if "UVW" in asked:
                out["UVW"] = rows.uvw
            if "FLAG_ROW" in asked:
                out["FLAG_ROW"] = np.zeros(rows.time.size, bool)
        flag = rows.flag if flag is None else flag | rows.flag
        for column in data_columns:
            if group_of_column(column) == group:
                out[column] = rows.data
    if "FLAG" in asked:
        out["FLAG"] = flag
    return out


def _whole(reader: PartitionReader, variables) -> PartitionRows:
    """Every row of a partition in one read."""
    chunks = list(reader.chunks(1 << 62, variables))
    if len(chunks) == 1:
        return chunks[0]
    raise RuntimeError(f"partition read in {len(chunks)} chunks, expected one")
