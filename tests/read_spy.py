"""Counting the main-table reads of a run, without changing them (tests only).

:func:`record_reads` wraps the real readers of :mod:`hitops.io.read` for the
duration of a ``with`` block (pytest's monkeypatch): every read still happens as
it would, and one ``(ms, columns, n_rows)`` entry per dataset or row range read
is appended to the list it yields.  The datasets' Measurement Sets are learnt
from the calls that open them.
"""

from __future__ import annotations

import contextlib

from hitops.io import read as msio


@contextlib.contextmanager
def record_reads(monkeypatch):
    log, source = [], {}
    open_main, open_groups = msio.open_main, msio.open_groups
    compute_columns, table_read = msio.compute_columns, msio.MainTable.read

    def opened_main(ms, *args, **kwargs):
        ds = open_main(ms, *args, **kwargs)
        source[id(ds)] = ms
        return ds

    def opened_groups(ms, *args, **kwargs):
        groups = open_groups(ms, *args, **kwargs)
        source.update({id(ds): ms for ds in groups.values()})
        return groups

    def computed(requests, *args, **kwargs):
        for ds, columns, rows in requests:
            n_all = int(ds.sizes["row"])
            n_rows = (len(range(*rows.indices(n_all))) if isinstance(rows, slice)
                      else len(rows) if rows is not None else n_all)
            log.append((source.get(id(ds), getattr(ds, "ms", None)),
                        tuple(c for c in columns if c != "ROWID") or
                        tuple(columns), n_rows))
        return compute_columns(requests, *args, **kwargs)

    def read_range(table, columns, start, stop):
        log.append((table.ms, tuple(columns), int(stop - start)))
        return table_read(table, columns, start, stop)

    with monkeypatch.context() as patch:
        patch.setattr(msio, "open_main", opened_main)
        patch.setattr(msio, "open_groups", opened_groups)
        patch.setattr(msio, "compute_columns", computed)
        patch.setattr(msio.MainTable, "read", read_range)
        yield log
