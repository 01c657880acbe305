"""Reading and writing main-table columns of a Measurement Set (dask-ms or python-casacore).

Only dask-ms's public API (``xds_from_ms``, ``xds_to_table``, ``Dataset``):
calibrate opens one dataset per (field, spectral window) group in time order
(:func:`open_groups`) where a set has several groups or a cluster runs the work,
diagnose one dataset of the whole table in storage order (:func:`open_main`);
callers lay rows out by (baseline, time) themselves.  A one-group set that this
process reads (:func:`open_for_reading`) is read with python-casacore instead, with
no dask graph: in storage order (:class:`StorageRows`, hitops/io/table_rows.py) or,
for a table not in time order cut into chunks, in time order through an index of its
row runs (hitops/io/time_sorted.py).  Writes go back through ``ROWID`` so any row
subset can be written.  Small subtables (SPECTRAL_WINDOW, POLARIZATION,
ANTENNA) are read with python-casacore (hitops/io/tables.py; a run's whole
metadata: hitops/io/metadata.py): they are a few rows and dask-ms adds only
overhead there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import ColumnError, MeasurementSetError
from . import tables
from .msv4.store import is_processing_set, is_zarr_store, open_store
from .table_rows import MAX_RUNS, MainTable, StorageRows, rows_reader  # noqa: F401 (re-exported)


def check_ms(ms: str | Path, role: str = "Measurement Set",
             processing_set_ok: bool = False) -> str:
    """Path of an existing Measurement Set as a string; raise if it is not one.

    ``processing_set_ok``: the step reads MSv4 processing sets too (calibrate): a zarr
    store is checked whole (hitops/io/msv4/store.py) and taken."""
    path = Path(ms)
    if not path.exists():
        raise MeasurementSetError(f"{role} '{ms}' does not exist; check the path")
    if processing_set_ok and is_zarr_store(path):
        return open_store(path, role).path
    if not (path / "table.dat").exists():
        if is_processing_set(path):
            raise MeasurementSetError(
                f"{role} '{ms}' is an MSv4 processing set; this step reads Measurement Sets v2 "
                "so far: give the v2 set it was converted from (docs/msv4.md)")
        raise MeasurementSetError(f"{role} '{ms}' is not a casacore table (no table.dat); "
                                  "give the Measurement Set directory")
    return str(path).rstrip("/")


def column_names(ms: str) -> List[str]:
    """Names of the main-table columns (of a processing set: the MSv2 names it answers to,
    hitops/io/msv4/columns.py)."""
    if is_processing_set(ms):
        from .msv4.columns import column_names as v4_columns
        return v4_columns(open_store(ms))
    return tables.column_names(ms)


def column_extent(ms: str, column: str) -> Tuple[int, tuple]:
    """(rows, the cell shape of ``column``: (n_chan, n_corr)) of a set, from its first row."""
    if is_processing_set(ms):
        from .msv4.group_rows import open_partition_groups
        groups = list(open_partition_groups(ms, [column]).values())
        return sum(g.n_rows for g in groups), groups[0].cell_shape(column) if groups else ()
    with tables.main_table(ms) as t:
        n = int(t.nrows())
        return n, tuple(t.getcell(column, 0).shape) if n else ()


def require_columns(ms: str, columns: Iterable[str], role: str = "Measurement Set",
                    hint: str = "") -> None:
    """Raise :class:`ColumnError` naming the first column ``ms`` lacks."""
    if is_processing_set(ms):
        from .msv4.columns import require_columns as v4_require
        return v4_require(open_store(ms), list(columns), role, hint)
    present = set(column_names(ms))
    for column in columns:
        if column not in present:
            raise ColumnError(f"{role} '{ms}' has no column {column}"
                              + (f"; {hint}" if hint else "")
                              + f" (columns present: {', '.join(sorted(present))})")


def read_subtable(ms: str, subtable: str, columns: Sequence[str]) -> Dict[str, np.ndarray]:
    """Whole columns of a subtable (``ANTENNA``, ``SPECTRAL_WINDOW``, ...)."""
    return tables.read_columns(f"{ms}::{subtable}", columns)


def selection_columns(ms: str) -> List[str]:
    """``["DATA_DESC_ID", "FIELD_ID"]`` when ``ms`` may mix spectral windows or fields.

    With one DATA_DESCRIPTION row and one FIELD row every row has the same
    values, so reading 2 x n_row integers to check them is skipped.
    """
    n_dd = tables.row_count(f"{ms}::DATA_DESCRIPTION")
    n_field = tables.row_count(f"{ms}::FIELD")
    return ["DATA_DESC_ID", "FIELD_ID"] if (n_dd > 1 or n_field > 1) else []


#: the main-table columns that tell one (field, spectral window) group from another
GROUP_COLUMNS = ("FIELD_ID", "DATA_DESC_ID")


def open_main(ms: str, columns: Sequence[str], chunk_rows: int = 1 << 21):
    """Lazy dask-ms dataset of the whole main table in storage order (ROWID coordinate)."""
    from daskms import xds_from_ms

    (ds,) = xds_from_ms(ms, columns=list(columns), index_cols=[], group_cols=[],
                        chunks={"row": int(chunk_rows)})
    return ds


def row_count(ms: str) -> int:
    """Rows of the main table (of a processing set: its cells that hold an integration)."""
    if is_processing_set(ms):
        from .msv4.group_rows import row_count as v4_rows
        return v4_rows(ms)
    return tables.row_count(ms)


def read_row_columns(ms: str, columns: Sequence[str]) -> Dict[str, np.ndarray]:
    """Per-row columns (TIME, INTERVAL, ANTENNA1, ANTENNA2, FLAG_ROW, ...) of every row: a
    Measurement Set's main table, or a processing set's rows (its groups in row order,
    read without their visibilities)."""
    if is_processing_set(ms):
        from .msv4.group_rows import open_partition_groups

        parts = []
        for source in sorted(open_partition_groups(ms, ["DATA"]).values(),
                             key=lambda s: s.row_base):
            with source.open() as table:
                parts.append(table.read_rows(list(columns), None))
        return {c: np.concatenate([p[c] for p in parts]) for c in columns}
    return tables.read_columns(ms, columns)


def open_for_reading(ms: str, columns: Sequence[str], chunks, time_ordered: bool,
                     direct: bool, local: bool = False,
                     mixed: Optional[bool] = None) -> Dict[tuple, object]:
    """What calibrate reads a set through, keyed by (FIELD_ID, DATA_DESC_ID).

    A set of one field and one spectral window (:func:`selection_columns`) is read
    with python-casacore, without dask-ms's query and graph (they cost more than the
    read itself), when this process reads and writes it:

    * ``direct``: read in one chunk on this process's threads, in storage order when
      ``time_ordered`` (a :class:`StorageRows` under (0, 0));
    * ``local``: read in several chunks on this process (no cluster): a set stored in
      time order (``time_ordered``) is a :class:`StorageRows` too; any other a
      :class:`hitops.io.time_sorted.TimeSortedRows` (read in time order without
      dask-ms's sort held for the run; ``chunks``: the rows of a read block).

    Any other set opens through :func:`open_groups`.  ``mixed``: the set may mix
    fields or windows (:func:`selection_columns`; ``SetMetadata.has_groups`` of a run
    that read its metadata), read from the subtables when None.  An MSv4 processing set
    gives one :class:`hitops.io.msv4.group_rows.PartitionSource` per group, whatever
    the rest says (a partition is stored in time order and read chunk by chunk).
    """
    if is_processing_set(ms):
        from .msv4.group_rows import open_partition_groups
        return open_partition_groups(ms, columns)
    if mixed is None:
        mixed = bool(selection_columns(ms))
    if (direct and time_ordered or local) and not mixed:
        block = chunks if isinstance(chunks, int) else max(chunks)
        with MainTable(ms) as table:
            # rows naming another FIELD/DATA_DESCRIPTION row than the one there is: the
            # grouped datasets carry that key, and the plan reports the damage (read in
            # blocks of a chunk's rows at most, as every read of a chunked run)
            n_rows = table.n_rows
            one_group = not any(np.any(values != 0)
                                for start in range(0, n_rows, max(1, int(block)))
                                for values in table.read(list(GROUP_COLUMNS), start,
                                                         min(n_rows, start + block)).values())
        if one_group and (time_ordered or not n_rows):
            return {(0, 0): StorageRows(ms, n_rows)}
        if one_group:
            from .time_sorted import sort_by_time

            reader = sort_by_time(ms, int(block))
            if reader is not None:   # else a TIME that is not finite: the index pass names it
                return {(0, 0): reader}
    return open_groups(ms, columns, chunks, time_ordered=time_ordered, mixed=mixed)


def is_time_ordered(ms: str, block_rows: int = 1 << 20) -> bool:
    """Whether the main table's TIME never decreases in storage order (read in blocks).

    Correlators and CASA write Measurement Sets in time order; such a table needs
    no sort to be read time chunk by time chunk.  A processing set's partitions are
    (time, baseline) grids: in time order.
    """
    if is_processing_set(ms):
        return True
    last = -np.inf
    with tables.main_table(ms) as t:
        n_row = t.nrows()
        for start in range(0, n_row, block_rows):
            times = t.getcol("TIME", start, min(block_rows, n_row - start))
            if times.size and (times[0] < last or np.any(times[1:] < times[:-1])):
                return False
            if times.size:
                last = times[-1]
    return True


def open_groups(ms: str, columns: Sequence[str], chunks,
                time_ordered: Optional[bool] = None,
                only: Optional[Tuple[int, int]] = None,
                mixed: Optional[bool] = None) -> Dict[tuple, object]:
    """Lazy dask-ms datasets of the main table, one per (FIELD_ID, DATA_DESC_ID), in time order.

    dask-ms's own grouping and ordering (``xds_from_ms`` with ``group_cols``
    and ``index_cols=["TIME"]``): each dataset holds the rows of one field and
    spectral window sorted by TIME, with their row numbers in ``ROWID``, so a
    time chunk is a contiguous slice of it whatever the table's storage order
    (baseline-major, shuffled or time-ordered).  ``chunks``: rows per dask
    block, or a tuple of block sizes (one block per time chunk).
    ``time_ordered``: the table is stored in time order (:func:`is_time_ordered`;
    checked when None), so the storage order is already the time order and
    dask-ms's sort is skipped.  ``mixed``: as in :func:`open_for_reading`.

    Which dask-ms query (measured on 10^7 rows per band, docs/performance.md):
    in storage order the grouping query costs less than the plain one (0.7 s
    against 1.45 s), so every set is grouped; sorted by TIME the grouping query
    is faster (1.2 s against 4.6 s) but holds more for the whole run (1.34-1.57 GB
    peak against 1.15 GB for the 10^7-row baseline-major pair, and 1138 MB
    against 964 MB at 4 x 10^6 rows, over the 1 GB default budget), so a set
    with one field and one spectral window (:func:`selection_columns`) is sorted
    by the plain query and returned under (0, 0).
    """
    from daskms import xds_from_ms

    if time_ordered is None:
        time_ordered = is_time_ordered(ms)
    if mixed is None:
        mixed = bool(selection_columns(ms))
    grouped = time_ordered or mixed
    # ``only`` (FIELD_ID, DATA_DESC_ID): that group alone, e.g. when ``chunks`` are one
    # group's time chunks (dask-ms would apply them to every group and refuse the others)
    where = {"taql_where": f"FIELD_ID=={int(only[0])} && DATA_DESC_ID=={int(only[1])}"} \
        if mixed and only is not None else {}
    datasets = xds_from_ms(ms, columns=list(columns), index_cols=[] if time_ordered else ["TIME"],
                           group_cols=list(GROUP_COLUMNS) if grouped else [],
                           chunks={"row": chunks}, **where)
    out = {}
    for ds in datasets:
        key = (int(ds.attrs.get("FIELD_ID", 0)), int(ds.attrs.get("DATA_DESC_ID", 0)))
        out[key] = ds
    return out


def _take_rows(array, rows: Optional[np.ndarray]):
    """Rows of a dask array, as slices of runs of consecutive rows where that is cheap.

    A time chunk of a baseline-major table is a few long runs; slicing each run and
    concatenating avoids dask's general fancy-index shuffle (seconds on 10^6 rows).
    """
    import dask.array as da

    if rows is None:
        return array
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size == 0:
        return array[:0]
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    if breaks.size > 4096:
        return array[rows]
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [rows.size]])
    parts = [array[int(rows[a]):int(rows[b - 1]) + 1] for a, b in zip(starts, stops)]
    return parts[0] if len(parts) == 1 else da.concatenate(parts, axis=0)


def compute_columns(requests, scheduler=None) -> List[Dict[str, np.ndarray]]:
    """Compute several datasets' columns in one dask call (tables are read concurrently).

    ``requests``: sequence of (dataset, columns, rows) with ``rows`` a ``slice``
    of the dataset's rows, ascending row positions, or None for all.  A slice
    aligned with the dataset's row blocks reads exactly those rows.  ``ROWID``
    may be asked for like a column.  Returns one dict per request.
    """
    import dask
    import dask.threaded

    graphs, direct = [], {}
    for i, (ds, columns, rows) in enumerate(requests):
        if isinstance(ds, StorageRows):   # python-casacore (or zarr), one table at a time
            with ds.open() as table:
                direct[i] = ds.read(table, list(columns), rows)
        elif isinstance(rows, slice):
            graphs.append({c: ds[c].data[rows] for c in columns})
        else:
            graphs.append({c: _take_rows(ds[c].data, rows) for c in columns})
    # a callable scheduler avoids dask probing for a distributed client on every call
    computed = iter(dask.compute(*graphs, scheduler=scheduler or dask.threaded.get)
                    if graphs else [])
    return [direct[i] if i in direct else next(computed) for i in range(len(requests))]


def read_main_columns(ms: str, columns: Sequence[str], rows: Optional[np.ndarray] = None,
                      chunk_rows: int = 1 << 21, scheduler=None) -> Dict[str, np.ndarray]:
    """Main-table columns as numpy arrays (storage order), optionally for some rows only.

    ``rows``: ascending row numbers to read (default all).  Uses dask-ms.
    """
    ds = open_main(ms, columns, chunk_rows)
    return compute_columns([(ds, list(columns), rows)], scheduler)[0]


def _single_block(value: np.ndarray, prefix: str = "hitops-write"):
    """A one-chunk dask array holding ``value`` itself (its graph layer named ``prefix-<uuid>``).

    ``da.from_array`` copies numpy input (dask >= 2024) and hashes it unless
    named: about 0.1 s for one 1.2 M-row, 4-correlation output column.  The
    array is not modified afterwards, so the graph can hold it directly.
    """
    import uuid

    import dask.array as da

    value = np.asarray(value)
    name = f"{prefix}-{uuid.uuid4().hex}"
    key = (name,) + (0,) * value.ndim
    return da.Array({key: value}, name, chunks=tuple((s,) for s in value.shape),
                    dtype=value.dtype)


def _put_rows(ms: str, rows: np.ndarray, arrays: Dict[str, np.ndarray]) -> None:
    """``arrays`` into existing columns at ``rows`` with python-casacore: one putcol per run
    of consecutive rows (a chunk of a table read in storage order is one run)."""
    order = np.argsort(rows, kind="stable")
    rows = rows[order]
    breaks = np.flatnonzero(np.diff(rows) != 1) + 1
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [rows.size]])
    with tables.main_table(ms, writable=True) as table:
        table.lock(write=True)
        for name, value in arrays.items():
            value = np.asarray(value)[order]
            for a, b in zip(starts, stops):
                table.putcol(name, value[a:b], int(rows[a]), int(b - a))


def write_main_columns(ms: str, rows: np.ndarray, arrays: Dict[str, np.ndarray],
                       dims: Dict[str, tuple], scheduler=None, direct: bool = False) -> None:
    """Write ``arrays`` (first axis = ``rows``) into main-table columns via dask-ms.

    Columns that do not exist are created by dask-ms from the array's dtype and shape.
    ``direct``: the columns exist and no dask-ms handle is open on the table (a
    one-chunk run that read it with python-casacore): written with python-casacore's
    putcol instead, without dask-ms's graph.
    """
    rows = np.asarray(rows, dtype=np.int64)
    if direct:
        _put_rows(ms, rows, arrays)
        return
    import dask
    import dask.threaded
    from daskms import Dataset, xds_to_table

    variables = {}
    for name, value in arrays.items():
        variables[name] = (dims[name], _single_block(value))
    # dask-ms expects the ROWID graph of a dataset it made ('row-...' layers) and warns
    # about any other; these row numbers are plain numbers, named the way it expects
    ds = Dataset(variables, coords={"ROWID": ("row", _single_block(rows, "row-hitops"))})
    writes = xds_to_table(ds, ms, columns=list(arrays))
    writes = writes if isinstance(writes, (list, tuple)) else [writes]
    # compute the write arrays, not the datasets: a dask-ms Dataset does not survive
    # pickling to distributed workers
    arrays_to_run = [var.data for w in writes for var in w.data_vars.values()]
    dask.compute(arrays_to_run, scheduler=scheduler or dask.threaded.get)
