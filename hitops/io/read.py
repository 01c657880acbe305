"""Reading and writing main-table columns of a Measurement Set through dask-ms.

One dataset per table (no grouping, storage order, ``ROWID`` coordinate), so
callers index rows themselves and lay them out by (baseline, time) with
:mod:`hitops.io.layout`; dask-ms's ``index_cols`` sort is not needed and its
TaQL cost is avoided.  Writes go back through the same ``ROWID`` so any row
subset can be written.  Small subtables (SPECTRAL_WINDOW, POLARIZATION,
ANTENNA) are read with python-casacore directly: they are a few rows and
dask-ms adds only overhead there.
"""

from __future__ import annotations

import contextlib
import weakref
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

from ..errors import ColumnError, MeasurementSetError


def check_ms(ms: str | Path, role: str = "Measurement Set") -> str:
    """Path of an existing Measurement Set as a string; raise if it is not one."""
    path = Path(ms)
    if not path.exists():
        raise MeasurementSetError(f"{role} '{ms}' does not exist; check the path")
    if not (path / "table.dat").exists():
        raise MeasurementSetError(f"{role} '{ms}' is not a casacore table (no table.dat); "
                                  "give the Measurement Set directory")
    return str(path).rstrip("/")


def column_names(ms: str) -> List[str]:
    """Names of the main-table columns."""
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t:
        return list(t.colnames())


def require_columns(ms: str, columns: Iterable[str], role: str = "Measurement Set",
                    hint: str = "") -> None:
    """Raise :class:`ColumnError` naming the first column ``ms`` lacks."""
    present = set(column_names(ms))
    for column in columns:
        if column not in present:
            raise ColumnError(f"{role} '{ms}' has no column {column}"
                              + (f"; {hint}" if hint else "")
                              + f" (columns present: {', '.join(sorted(present))})")


def read_subtable(ms: str, subtable: str, columns: Sequence[str]) -> Dict[str, np.ndarray]:
    """Whole columns of a subtable (``ANTENNA``, ``SPECTRAL_WINDOW``, ...)."""
    from casacore import tables as pt

    with pt.table(f"{ms}::{subtable}", ack=False) as t:
        return {c: (t.getcol(c) if t.nrows() else np.array([])) for c in columns}


def selection_columns(ms: str) -> List[str]:
    """``["DATA_DESC_ID", "FIELD_ID"]`` when ``ms`` may mix spectral windows or fields.

    With one DATA_DESCRIPTION row and one FIELD row every row has the same
    values, so reading 2 x n_row integers to check them is skipped.
    """
    from casacore import tables as pt

    with pt.table(f"{ms}::DATA_DESCRIPTION", ack=False) as t:
        n_dd = t.nrows()
    with pt.table(f"{ms}::FIELD", ack=False) as t:
        n_field = t.nrows()
    return ["DATA_DESC_ID", "FIELD_ID"] if (n_dd > 1 or n_field > 1) else []


#: where each dataset made by open_main came from (table, row chunk), so a row subset can
#: be read as its own dask-ms dataset (see compute_columns)
_SOURCES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def open_main(ms: str, columns: Sequence[str], chunk_rows: int = 1 << 21):
    """Lazy dask-ms dataset of the main table: one group, storage order, ROWID coordinate.

    Storage order is what every caller here wants (rows are laid out by
    (baseline, time) afterwards), so the dataset is built by dask-ms's own
    dataset factory with the row order given directly, not found by dask-ms's
    ordering query ``SELECT ROWID() AS __tablerow__ FROM $1``: that query
    evaluates an expression on every row (about 0.2 s per 1.2 M-row table
    here, holding the GIL) only to return 0..n_row-1.  Reads still run through
    dask-ms (its TableProxy, executor and getcol wrappers), and the result is
    identical to ``xds_from_ms(ms, columns, index_cols=[], group_cols=[])``
    (tests/test_io_read.py checks it).  If a dask-ms release changes those
    internals, the public call is used instead.
    """
    columns = list(columns)
    try:
        ds = _storage_order_dataset(ms, columns, int(chunk_rows))
    except (ImportError, AttributeError, TypeError):   # dask-ms internals moved
        from daskms import xds_from_ms

        (ds,) = xds_from_ms(ms, columns=columns, index_cols=[], group_cols=[],
                            chunks={"row": int(chunk_rows)})
        return ds
    _SOURCES[ds] = (ms, int(chunk_rows))
    return ds


def open_main_blocks(ms: str, columns: Sequence[str], block_sizes: Sequence[int],
                     rows: Optional[np.ndarray] = None):
    """Lazy dask-ms dataset whose row chunks are given blocks (e.g. time chunks).

    ``rows``: the row numbers in block order (each block's ascending), default
    0..n_row-1; ``block_sizes`` add up to their number.  Slices aligned with
    the blocks (:func:`compute_columns`) read exactly one block's rows, so a
    chunked run builds one dataset per table instead of one per chunk and read
    (about 12 ms each, measured).
    """
    sizes = tuple(int(n) for n in block_sizes)
    ds = _storage_order_dataset(ms, list(columns), sizes, rows=rows)
    _SOURCES[ds] = (ms, max(sizes))
    return ds


def _storage_order_dataset(ms: str, columns: List[str], chunk_rows,
                           rows: Optional[np.ndarray] = None):
    """dask-ms Dataset of ``columns`` in storage order without the ordering TaQL query.

    ``rows``: ascending row numbers to read (default every row).  They become the
    dataset's ROWID and dask-ms reads exactly their runs of consecutive rows.
    """
    import dask.array as da
    from dask.array.core import normalize_chunks
    from daskms.ordering import row_run_factory
    from daskms.reads import DatasetFactory

    class _StorageOrderFactory(DatasetFactory):
        def datasets(self):
            table_proxy = self._table_proxy_factory()
            if rows is None:
                n_row = table_proxy.nrows().result()
                chunks = normalize_chunks(self.chunks[0]["row"], shape=(n_row,))
                # the rows dask-ms's query returns for no index_cols and no where clause
                order = da.arange(n_row, chunks=chunks, dtype=np.int64)
            else:
                order = _blocks_of(np.asarray(rows), self.chunks[0]["row"])
            row_runs = order.map_blocks(row_run_factory, sort_dir="read", dtype=object)
            return self._single_dataset(table_proxy, (order, row_runs))

    # the keyword arguments xds_from_ms passes for a Measurement Set main table
    return _StorageOrderFactory(ms, columns, [], [], chunks={"row": chunk_rows},
                                table_schema="MS", context="ms").datasets()


def _blocks_of(rows: np.ndarray, chunks) -> "dask.array.Array":
    """int64 dask array of ``rows`` whose blocks are views of it, converted block by block.

    ``da.from_array`` would copy and hash the whole array; a chunked run's row
    numbers (int32 for tables not in time order) stay one array in memory.
    """
    import uuid

    import dask.array as da
    from dask.array.core import normalize_chunks

    (sizes,) = normalize_chunks(chunks, shape=rows.shape)
    name = f"hitops-rows-{uuid.uuid4().hex}"
    edges = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    graph = {(name, k): rows[edges[k]:edges[k + 1]] for k in range(len(sizes))}
    blocks = da.Array(graph, name, chunks=(tuple(sizes),), dtype=rows.dtype)
    return blocks if rows.dtype == np.int64 else blocks.astype(np.int64)


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


#: active recorders of main-table reads (see record_reads)
_RECORDERS: List[list] = []


@contextlib.contextmanager
def record_reads():
    """Record every main-table read made through :func:`compute_columns`.

    Yields a list that receives one ``(ms, columns, n_rows)`` tuple per dataset
    read, so tests can check how many rows a run holds at once (the reads are
    real; nothing is replaced).
    """
    log = []
    _RECORDERS.append(log)
    try:
        yield log
    finally:
        _RECORDERS.remove(log)


def _record(ds, columns, rows) -> None:
    source = _SOURCES.get(ds)
    n_all = int(ds[list(columns)[0]].shape[0])
    n_rows = (len(range(*rows.indices(n_all))) if isinstance(rows, slice)
              else len(rows) if rows is not None else n_all)
    entry = (source[0] if source else None, tuple(columns), n_rows)
    for log in _RECORDERS:
        log.append(entry)


def compute_columns(requests, scheduler=None) -> List[Dict[str, np.ndarray]]:
    """Compute several datasets' columns in one dask call (tables are read concurrently).

    ``requests``: sequence of (dataset, columns, rows) with ``rows`` ascending
    row positions of the dataset, a ``slice`` of them, or None for all.  Returns
    one dict per request.  A slice aligned with the dataset's row chunks (see
    ``open_main(chunk_rows=)``) reads exactly those rows and builds no dataset.
    """
    import dask
    import dask.threaded

    graphs = []
    for ds, columns, rows in requests:
        if _RECORDERS:
            _record(ds, columns, rows)
        source = _SOURCES.get(ds)
        if isinstance(rows, slice):
            graphs.append({c: ds[c].data[rows] for c in columns})
        elif rows is not None and source is not None and len(rows):
            # a dataset of just these rows: dask-ms reads their runs and nothing else
            # (slicing the whole-table dataset would read every row chunk a run touches)
            sub = _storage_order_dataset(source[0], list(columns), source[1], rows=rows)
            graphs.append({c: sub[c].data for c in columns})
        else:
            graphs.append({c: _take_rows(ds[c].data, rows) for c in columns})
    # a callable scheduler avoids dask probing for a distributed client on every call
    return list(dask.compute(*graphs, scheduler=scheduler or dask.threaded.get))


def read_main_columns(ms: str, columns: Sequence[str], rows: Optional[np.ndarray] = None,
                      chunk_rows: int = 1 << 21, scheduler=None) -> Dict[str, np.ndarray]:
    """Main-table columns as numpy arrays (storage order), optionally for some rows only.

    ``rows``: ascending row numbers to read (default all).  Uses dask-ms.
    """
    ds = open_main(ms, columns, chunk_rows)
    return compute_columns([(ds, list(columns), rows)], scheduler)[0]


def _single_block(value: np.ndarray):
    """A one-chunk dask array holding ``value`` itself.

    ``da.from_array`` copies numpy input (dask >= 2024) and hashes it unless
    named: about 0.1 s for one 1.2 M-row, 4-correlation output column.  The
    array is not modified afterwards, so the graph can hold it directly.
    """
    import uuid

    import dask.array as da

    value = np.asarray(value)
    name = f"hitops-write-{uuid.uuid4().hex}"
    key = (name,) + (0,) * value.ndim
    return da.Array({key: value}, name, chunks=tuple((s,) for s in value.shape),
                    dtype=value.dtype)


def write_main_columns(ms: str, rows: np.ndarray, arrays: Dict[str, np.ndarray],
                       dims: Dict[str, tuple], scheduler=None) -> None:
    """Write ``arrays`` (first axis = ``rows``) into main-table columns via dask-ms.

    Columns that do not exist are created by dask-ms from the array's dtype and shape.
    """
    import dask
    import dask.array as da
    import dask.threaded
    from daskms import Dataset, xds_to_table

    rows = np.asarray(rows, dtype=np.int64)
    n = rows.size
    variables = {}
    for name, value in arrays.items():
        variables[name] = (dims[name], _single_block(value))
    ds = Dataset(variables, coords={"ROWID": ("row", _single_block(rows))})
    writes = xds_to_table(ds, ms, columns=list(arrays))
    writes = writes if isinstance(writes, (list, tuple)) else [writes]
    # compute the write arrays, not the datasets: a dask-ms Dataset does not survive
    # pickling to distributed workers
    arrays_to_run = [var.data for w in writes for var in w.data_vars.values()]
    dask.compute(arrays_to_run, scheduler=scheduler or dask.threaded.get)
