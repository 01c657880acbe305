"""Every python-casacore table call of hitops: the MSv2 and calibration-table backend's seam.

A Measurement Set v2 and a CASA calibration table are casacore tables on disk;
this module is the one place hitops opens them (tests/test_layout.py fails on a
``casacore.tables`` open anywhere outside hitops/io/, hitops/casa/ and
hitops/testing/, and inside hitops/io/ anywhere but here; dask-ms's reads and
writes are hitops/io/read.py's).  What it offers, by what the caller does:

* hold a table open: :func:`main_table` (a set's main table), :func:`subtable`
  (``ms::ANTENNA``, ...), :func:`calibration_subtable` (a caltable's ``ANTENNA``, ...,
  the directory CASA writes beside its main table), :func:`open_table` (any path);
  each returns python-casacore's table, a context manager, read-only unless
  ``writable=True``;
* read without holding: :func:`read_columns` (whole columns of a table or subtable),
  :func:`row_count`, :func:`column_names`;
* create: :func:`new_measurement_set` (casacore's ``default_ms`` with a description and data
  managers, :func:`array_column` / :func:`table_description` for the description).

A set's metadata (antennas, fields, windows, data descriptions, polarizations) is
read once per set through :func:`hitops.io.metadata.read_metadata`, which is the
backend-neutral entry: an MSv4 processing set (xradio/zarr) plugs in there beside
this module, not here.  No module state: every call opens and closes its table
(or returns it open to the caller's ``with``).
"""

from __future__ import annotations

from typing import Dict, List, Mapping, Sequence

import numpy as np


def _tables():
    # imported when a table is opened: hitops imports without python-casacore's start-up
    from casacore import tables
    return tables


def open_table(path: str, writable: bool = False, user_locks: bool = False):
    """The casacore table at ``path`` (a directory, or ``ms::SUBTABLE``), open; use in ``with``.

    ``user_locks``: casacore's ``lockoptions="user"``, the caller takes and releases the
    locks itself (hitops/io/access.py: the run lock, the wait for another holder).
    """
    if user_locks:
        return _tables().table(str(path), readonly=not writable, ack=False, lockoptions="user")
    return _tables().table(str(path), readonly=not writable, ack=False)


def main_table(ms: str, writable: bool = False, user_locks: bool = False):
    """The main table of Measurement Set ``ms``, open; use in ``with``."""
    return open_table(ms, writable, user_locks)


def subtable(ms: str, name: str, writable: bool = False):
    """Subtable ``name`` (ANTENNA, FIELD, SPECTRAL_WINDOW, ...) of ``ms``, open; use in ``with``."""
    return open_table(f"{ms}::{name}", writable)


def calibration_subtable(path: str, name: str, writable: bool = False):
    """Subtable ``name`` of the CASA calibration table at ``path``, open; use in ``with``."""
    return open_table(f"{path}/{name}", writable)


def read_columns(path: str, columns: Sequence[str]) -> Dict[str, np.ndarray]:
    """Whole columns of the table at ``path`` (empty arrays for a table of no rows)."""
    with open_table(path) as t:
        return {c: (t.getcol(c) if t.nrows() else np.array([])) for c in columns}


def row_count(path: str) -> int:
    """Rows of the table at ``path``."""
    with open_table(path) as t:
        return int(t.nrows())


def column_names(path: str) -> List[str]:
    """Names of the columns of the table at ``path``."""
    with open_table(path) as t:
        return list(t.colnames())


def array_column(name: str, value, shape: Sequence[int], valuetype: str, comment: str) -> dict:
    """Description of a fixed-shape array column (casacore ``makearrcoldesc``): every cell
    ``shape``, so the tiled storage managers hitops gives them can lay out whole rows."""
    fixed_shape = 4  # casacore ColumnDesc::FixedShape (tables/Tables/ColumnDesc.h)
    return _tables().makearrcoldesc(name, value, shape=list(shape), valuetype=valuetype,
                                    options=fixed_shape, comment=comment)


def column_description(name: str, description: dict) -> dict:
    """A column description named ``name`` from another column's (casacore ``makecoldesc``)."""
    return _tables().makecoldesc(name, description)


def table_description(columns: Sequence[dict]) -> dict:
    """A table description of ``columns`` (casacore ``maketabdesc``)."""
    return _tables().maketabdesc(list(columns))


def new_measurement_set(path: str, description: dict, data_managers: Mapping[str, dict]):
    """A new Measurement Set at ``path`` (casacore ``default_ms``: the standard columns and
    subtables, plus ``description``'s columns), open for writing; close it when done."""
    return _tables().default_ms(str(path), description, dict(data_managers))


def variable_array_column(name: str, value, ndim: int, valuetype: str) -> dict:
    """Description of an array column whose cells have ``ndim`` axes of any length (a CASA
    flag version's FLAG, as flagmanager writes it)."""
    return _tables().makearrcoldesc(name, value, ndim=ndim, valuetype=valuetype)


def scalar_column(name: str, value, valuetype: str) -> dict:
    """Description of a scalar column (casacore ``makescacoldesc``)."""
    return _tables().makescacoldesc(name, value, valuetype=valuetype)


def new_table(path: str, description: dict, n_rows: int, data_managers: Mapping[str, dict]):
    """A new plain table at ``path`` with ``n_rows`` rows, open for writing; use in ``with``."""
    return _tables().table(str(path), description, nrow=int(n_rows), dminfo=dict(data_managers),
                           ack=False)
