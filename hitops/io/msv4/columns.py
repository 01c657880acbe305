"""MSv2 column names in terms of a processing set's data groups: the one place they map.

hitops's options and stages name Measurement Set v2 columns (``--target-column DATA``,
``--output-column PWC_DATA``, FLAG, WEIGHT, ...).  An MSv4 partition holds no columns
but named data groups (``data_groups``: which correlated data, flag, weight and UVW
belong together), so on a processing set:

* a data column names a group: ``DATA`` is the ``base`` group (xradio converts an
  MSv2's DATA into it), ``<NAME>_DATA`` the group ``<name>`` (CORRECTED_DATA ->
  ``corrected``, MODEL_DATA -> ``model``, PWC_DATA -> ``pwc``), any other name the group
  of its lower-case form; :func:`group_of_column` and :func:`column_of_group` are inverse;
* ``FLAG`` is the flag of the group the band reads its data from, ``WEIGHT`` its weight
  (averaged over the channels: an MSv2's WEIGHT is per row and correlation), ``SIGMA``
  1/sqrt(WEIGHT) (the MSv2 convention, as CASA writes it; MSv4 keeps no sigma);
* the per-row columns the readers give (:data:`ROW_COLUMNS`) are recovered by
  hitops/io/msv4/rows.py; an MSv4 has no FLAG_ROW (xradio folds it into the flags) and
  one INTERVAL per partition (the time coordinate's ``integration_time``).
"""

from __future__ import annotations

from typing import List, Sequence

from ...errors import ColumnError
from .store import ProcessingSetStore

#: the data group an MSv2's DATA becomes
BASE_GROUP = "base"
#: columns every partition has, as hitops's readers give them
ROW_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "INTERVAL", "FLAG_ROW",
               "FIELD_ID", "DATA_DESC_ID", "ROWID")
#: columns that follow the band's data group rather than naming one
GROUP_MEMBERS = ("FLAG", "WEIGHT", "SIGMA", "UVW")


def group_of_column(column: str) -> str:
    """The data group a data column names (DATA -> base, CORRECTED_DATA -> corrected)."""
    name = str(column).strip()
    if name == "DATA":
        return BASE_GROUP
    if name.endswith("_DATA") and len(name) > len("_DATA"):
        name = name[:-len("_DATA")]
    return name.lower()


def column_of_group(group: str) -> str:
    """The data column that names ``group`` (base -> DATA, corrected -> CORRECTED_DATA)."""
    return "DATA" if group == BASE_GROUP else f"{group.upper()}_DATA"


def is_data_column(column: str) -> bool:
    """Whether ``column`` names a data group (not a row column nor a group member)."""
    return column not in ROW_COLUMNS and column not in GROUP_MEMBERS


def band_group(columns: Sequence[str]) -> str:
    """The data group a band reads: that of the first data column it asks for (its data
    column comes first: calibrate/inputs.py); FLAG, WEIGHT and SIGMA are that group's."""
    return next((group_of_column(c) for c in columns if is_data_column(c)), BASE_GROUP)


def column_names(store: ProcessingSetStore) -> List[str]:
    """The MSv2 names a processing set answers to: the row columns, the members of a
    group, and one data column per data group that every partition holds."""
    common = None
    for entry in store.partitions:
        names = {g.name for g in entry.data_groups}
        common = names if common is None else common & names
    groups = sorted(common or ())
    members = ["FLAG", "UVW"] + (["WEIGHT", "SIGMA"] if all(
        g.weight for e in store.partitions for g in e.data_groups if g.name in groups) else [])
    return [c for c in ROW_COLUMNS if c != "ROWID"] + members + [column_of_group(g)
                                                                 for g in groups]


def require_columns(store: ProcessingSetStore, columns: Sequence[str], role: str,
                    hint: str = "") -> None:
    """Raise :class:`ColumnError` naming the first column the processing set cannot give."""
    present = set(column_names(store))
    for column in columns:
        if column not in present:
            what = (f"data group '{group_of_column(column)}' (the column {column})"
                    if is_data_column(column) else f"column {column}")
            raise ColumnError(f"{role} '{store.path}' (an MSv4 processing set) has no {what}"
                              + (f"; {hint}" if hint else "")
                              + f" (it answers to: {', '.join(sorted(present))})")
