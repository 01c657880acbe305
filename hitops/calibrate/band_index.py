"""Stage 3 of ``hitops calibrate`` (plan), its first pass: what is kept of each band's rows.

:func:`index_bands` reads the per-row metadata (:data:`INDEX_COLUMNS`) of
each :class:`BandSource` in blocks of at most ``block_rows`` rows and builds one
:class:`BandIndex` per band, whole, with summaries (distinct times and their row counts, antenna pairs, scans,
smallest INTERVAL), and for a band in time order each row's antenna pair (two
bytes per row), so the checks of every chunk need not read the metadata again
(:meth:`hitops.calibrate.chunks.GroupMatch.check`).  A table stored out of time
order and read in time order (:class:`hitops.io.time_sorted.TimeSortedRows`) is
indexed in storage order instead, each row's pair key then placed at its position
in the time order (:func:`_index_in_storage_order`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import MeasurementSetError, TimeChangedError
from ..io import read as msio
from ..io.match import distinct_counts, distinct_ints
from ..io.time_sorted import TimeSortedRows
from ..kernels.sorted_runs import lookup_sorted, time_order_places

#: per-row columns read in the first (index) pass
INDEX_COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "INTERVAL", "FLAG_ROW"]
#: per-row columns a chunk needs
ROW_COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "FLAG_ROW"]


@dataclass(frozen=True)
class BandSource:
    """Where one band's (field, spectral window) group is read from.

    ``ds`` is the group's dask-ms dataset (:func:`hitops.io.read.open_groups`): in time
    order (``ds_in_time_order``), so the rows of any time range are one contiguous
    slice of it, or in storage order for a band read whole in one chunk.
    """

    ms: str
    ds: object
    n_row: int
    n_ant: int
    key: tuple = (0, 0)                   # (FIELD_ID, DATA_DESC_ID) of the group
    time_ordered: bool = False            # stored in time order: no sort when reopened
    ds_in_time_order: bool = True         # False: read whole in one chunk, storage order


@dataclass(frozen=True)
class BandIndex:
    """Summary of one band's group, built whole by :func:`index_bands`, then only read.

    Per row only ``pair_key`` is kept (a band in time order read in several blocks);
    ``whole`` holds every row's metadata of a band read in one block.
    """

    ms: str
    n_row: int
    n_ant: int
    key: tuple                            # (FIELD_ID, DATA_DESC_ID) of the group
    time_ordered: bool                    # stored in time order: no sort when reopened
    ds_in_time_order: bool                # False: read whole in one chunk, storage order
    unique_time: np.ndarray               # sorted distinct TIME values
    time_rows: np.ndarray                 # rows at each distinct TIME value
    row_start: np.ndarray                 # first row (dataset position) of each distinct TIME
    pair_present: np.ndarray              # (n_ant * n_ant,) ANTENNA1 * n_ant + ANTENNA2 used
    scans: np.ndarray                     # distinct SCAN_NUMBER values
    min_interval: float                   # smallest positive INTERVAL (inf if none)
    whole: Optional[Dict[str, np.ndarray]]   # every row's metadata, when one block
    pair_key: Optional[np.ndarray]        # per row: ANTENNA1 * n_ant + ANTENNA2 (see index_bands)
    time_scan: Optional[np.ndarray]       # SCAN_NUMBER of the last row at each distinct TIME

    def rows_in(self, lo: float, hi: float) -> slice:
        """Dataset positions of the rows with lo <= TIME < hi (they follow each other)."""
        if not self.ds_in_time_order:
            raise RuntimeError(f"{self.ms}: a part of the track was asked of a band read in "
                               "storage order (one chunk only); this is a hitops bug")
        u0, u1 = np.searchsorted(self.unique_time, [lo, hi])
        return slice(int(self.row_start[u0]), int(self.row_start[u1]))

    def times_of(self, rows: slice) -> slice:
        """The distinct times (indices into ``unique_time``) whose rows are ``rows``, a
        slice given by :meth:`rows_in`."""
        u0, u1 = np.searchsorted(self.row_start, [rows.start, rows.stop])
        return slice(int(u0), int(u1))


class _OrderedTimes:
    """Distinct times and rows per time of a band read block by block in time order,
    joined once at the end: a join per block copies every time so far (O(blocks x
    times): 0.6 s at 10^7 rows in 100 blocks as a sort, 0.2 s as a copy)."""

    def __init__(self):
        self.pieces: List[Tuple[np.ndarray, np.ndarray]] = []

    def add(self, values: np.ndarray, counts: np.ndarray) -> None:
        """A block's distinct times (ascending, none before the last block's last time) and
        rows per time; a time the block boundary cut adds its rows to that time."""
        counts = np.array(counts, dtype=np.int64)
        if values.size and self.pieces and values[0] == self.pieces[-1][0][-1]:
            self.pieces[-1][1][-1] += counts[0]
            values, counts = values[1:], counts[1:]
        if values.size:
            self.pieces.append((values, counts))

    def join(self) -> Tuple[np.ndarray, np.ndarray]:
        """(sorted distinct times, rows per time) of every block added."""
        return (np.concatenate([v for v, _ in self.pieces]),
                np.concatenate([c for _, c in self.pieces]))


class _Pass:
    """What the index pass gathers of one band, block by block (private to it)."""

    def __init__(self, source: BandSource, block_rows: int):
        self.source = source
        self.last_time = -np.inf
        self.unique, self.counts = np.zeros(0), np.zeros(0, np.int64)
        self.ordered_times = _OrderedTimes()
        self.scans, self.time_scans = [], []
        self.pair_present = np.zeros(source.n_ant * source.n_ant, dtype=bool)
        self.min_interval = np.inf
        self.whole = None
        self.pair_key = None
        if source.ds_in_time_order and source.n_row > block_rows:
            key_type = np.uint16 if source.n_ant * source.n_ant <= 1 << 16 else np.uint32
            self.pair_key = np.empty(source.n_row, dtype=key_type)

    def index(self) -> BandIndex:
        src = self.source
        if self.ordered_times.pieces:
            self.unique, self.counts = self.ordered_times.join()
        time_scan = None
        if self.pair_key is not None:
            # blocks in time order: a time cut by a block boundary takes the later block's
            time_scan = np.empty(self.unique.size, dtype=np.int64)
            for times, scans in self.time_scans:
                time_scan[np.searchsorted(self.unique, times)] = scans
        return BandIndex(ms=src.ms, n_row=src.n_row, n_ant=src.n_ant, key=src.key,
                         time_ordered=src.time_ordered, ds_in_time_order=src.ds_in_time_order,
                         unique_time=self.unique, time_rows=self.counts,
                         row_start=np.concatenate([[0], np.cumsum(self.counts)]),
                         pair_present=self.pair_present,
                         scans=np.unique(np.concatenate(self.scans)),
                         min_interval=self.min_interval, whole=self.whole,
                         pair_key=self.pair_key, time_scan=time_scan)


def index_bands(sources: List[BandSource], columns: List[List[str]], block_rows: int,
                scheduler=None) -> List[BandIndex]:
    """One :class:`BandIndex` per band, from blocks of at most ``block_rows`` rows.

    A band whose dataset is the whole table in storage order (one
    field/spectral-window group, stored in time order or read whole) is read
    with python-casacore's getcol, row range by row range (exactly these
    columns, no dask graph); other bands' blocks are read in one dask call (the
    tables concurrently), as slices of each band's dataset (whose dask blocks
    are ``block_rows`` long).  A band that fits in one block keeps that block's
    metadata in ``whole`` (it is bounded by ``block_rows`` and saves reading it
    again).  A band in time order read in several blocks keeps each row's
    antenna pair (``pair_key``: 2 bytes per row up to 256 stations) and the scan
    at each time (``time_scan``): with the rows' times, which follow from their
    positions, that is all the checks of every chunk need, so they read nothing
    again (:meth:`hitops.calibrate.chunks.GroupMatch.check`).  A processing set's group
    in several blocks reads no column: its partition's grid gives all of this
    (:func:`_index_from_grid`).
    """
    passes = [_Pass(source, block_rows) for source in sources]
    n_blocks = max(-(-s.n_row // block_rows) for s in sources)
    # a table read in time order through its runs, in several blocks: indexed in storage
    # order instead (contiguous reads), each row then placed in the time order
    by_storage = [isinstance(p.source.ds, TimeSortedRows) and p.pair_key is not None
                  for p in passes]
    for band, cols, storage in zip(passes, columns, by_storage):
        if storage:
            _index_in_storage_order(band, cols, block_rows)
    # a processing set's group in several blocks: its summaries follow from the grid
    # counted when it was opened, and only the rows' antennas are made (no column read)
    by_grid = [not storage and _index_from_grid(band, block_rows)
               for band, storage in zip(passes, by_storage)]
    by_storage = [storage or grid for storage, grid in zip(by_storage, by_grid)]
    with contextlib.ExitStack() as stack:
        tables = [_storage_order_table(source, stack) for source in sources]
        for k in range(n_blocks):
            requests, which, direct = [], [], []
            for band, cols, table, storage in zip(passes, columns, tables, by_storage):
                a, b = k * block_rows, min(band.source.n_row, (k + 1) * block_rows)
                if a >= b or storage:
                    continue
                if table is not None:   # storage order: python-casacore, no dask graph
                    meta = table.read(cols, a, b)
                    meta["ROWID"] = np.arange(a, b)
                    direct.append(((band, a, b), meta))
                else:
                    one_block = a == 0 and b == band.source.n_row
                    requests.append((band.source.ds,
                                     list(cols) + (["ROWID"] if one_block else []), slice(a, b)))
                    which.append((band, a, b))
            read = list(zip(which, msio.compute_columns(requests, scheduler))) if requests else []
            for (band, a, b), meta in direct + read:
                _summarise_block(band, a, b, meta)
                if a == 0 and b == band.source.n_row:
                    band.whole = {c: meta[c] for c in ROW_COLUMNS + ["ROWID"]}
    return [band.index() for band in passes]


def _index_in_storage_order(band: "_Pass", columns: List[str], block_rows: int) -> None:
    """Index a band whose dataset is its table in (TIME, row number) order
    (:class:`hitops.io.time_sorted.TimeSortedRows`) from two passes in storage order.

    Read through its runs, each block of the time order costs one getcol per run of
    rows (a baseline-major table has one run per baseline and bucket), several times
    the cost of the same rows read as one range.  The summaries do not depend on the
    order, so the first pass reads contiguous blocks; the second reads TIME, the
    antennas and SCAN_NUMBER again and puts each row's pair key at its position in the
    time order, row_start of its time plus the rows of that time before it (rows
    ascend within a block and blocks follow each other, as the order's ties do), and
    each time's scan is that of its last row there.
    """
    src = band.source
    pair_key, band.pair_key = band.pair_key, None   # the first pass keeps no per-row key
    with msio.MainTable(src.ms) as table:
        if table.n_rows != src.n_row:
            raise RuntimeError(f"{src.ms}: a time-sorted band is not its whole table; this "
                               "is a hitops bug")
        for a in range(0, src.n_row, block_rows):
            b = min(src.n_row, a + block_rows)
            meta = table.read(columns, a, b)
            meta["ROWID"] = np.arange(a, b)
            _summarise_block(band, a, b, meta, storage_order=True)
        row_start = np.concatenate([[0], np.cumsum(band.counts)]).astype(np.int64)
        seen = np.zeros(band.unique.size, dtype=np.int64)
        time_scan = np.zeros(band.unique.size, dtype=np.int64)
        for a in range(0, src.n_row, block_rows):
            b = min(src.n_row, a + block_rows)
            meta = table.read(["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER"], a, b)
            at = lookup_sorted(np.asarray(meta["TIME"], dtype=np.float64), band.unique)
            if at.size and at.min() < 0:
                raise TimeChangedError(src.ms)
            places, seen, time_scan = time_order_places(
                at, np.asarray(meta["SCAN_NUMBER"], dtype=np.int64), row_start, seen,
                time_scan)
            pair_key[places] = meta["ANTENNA1"].astype(np.int64) * src.n_ant + meta["ANTENNA2"]
    if not np.array_equal(seen, band.counts):
        raise TimeChangedError(src.ms)
    band.pair_key = pair_key
    band.time_scans = [(band.unique, time_scan)]


def _index_from_grid(band: "_Pass", block_rows: int) -> bool:
    """Index a processing set's group (:class:`hitops.io.msv4.group_rows.PartitionSource`)
    read in several blocks from its time steps; False (nothing done) for any other band.

    Its rows are the grid's present cells in time then baseline order, so the row pass's
    summaries are the steps' own: distinct times are the steps holding rows, rows per time
    their counts, the scan at each time the step's, INTERVAL the partition's integration
    time, FLAG_ROW nowhere set.  Each row's pair key comes from its cell's baseline.  At
    10^7 rows a band this took the index pass from 1.3 s to 0.2 s (docs/performance.md).
    A group whose step times are not finite and ascending takes the row pass, whose
    checks say what is wrong.
    """
    src = band.source
    if band.pair_key is None or not hasattr(src.ds, "time_steps"):
        return False
    steps = src.ds.time_steps()
    held = steps.n_rows > 0
    times, counts = steps.time[held], steps.n_rows[held].astype(np.int64)
    if int(counts.sum()) != src.n_row or not np.all(np.isfinite(times)) or \
            np.any(times[1:] <= times[:-1]):
        return False
    band.unique, band.counts = times, counts
    scans = steps.scan_number[held]
    band.time_scans = [(times, scans)]
    band.scans = [distinct_ints(scans)]
    if np.isfinite(steps.interval) and steps.interval > 0:
        band.min_interval = float(steps.interval)
    for a in range(0, src.n_row, block_rows):
        b = min(src.n_row, a + block_rows)
        ant1, ant2 = src.ds.antennas(a, b)
        key = ant1.astype(np.int64) * src.n_ant + ant2
        band.pair_present |= np.bincount(key, minlength=band.pair_present.size) > 0
        band.pair_key[a:b] = key
    return True


def _storage_order_table(source: BandSource, stack: contextlib.ExitStack):
    """The band's table held open when its dataset positions are the table's row numbers
    (one group, stored in time order or read in storage order); else None (dask-ms's
    dataset is read: a group of several, or sorted by TIME)."""
    if not (source.time_ordered or not source.ds_in_time_order) or \
            not getattr(source.ds, "positions_are_rows", True):
        return None   # (a processing set's group: its ROWID is not its position)
    table = stack.enter_context(msio.MainTable(source.ms))
    return table if table.n_rows == source.n_row else None


def _summarise_block(band: _Pass, a: int, b: int, meta: Dict[str, np.ndarray],
                     storage_order: bool = False) -> None:
    """Add one block's rows to the band's summaries.  ``storage_order``: a block of a
    table indexed in storage order (:func:`_index_in_storage_order`): its times are not
    in order, and the rows' pair keys are placed by the second pass."""
    src = band.source
    t = np.asarray(meta["TIME"], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        row = int(meta["ROWID"][bad]) if "ROWID" in meta else a + bad
        raise MeasurementSetError(f"{src.ms}: TIME of row {row} is {t[bad]}; rows without "
                                  "a valid time cannot be matched: remove them (CASA split "
                                  "with a time range) or repair the TIME column")
    if storage_order:   # any order: counted against the times known so far
        band.unique, band.counts = _add_times(band.unique, band.counts, t)
    else:
        if not src.ds_in_time_order:
            if not (a == 0 and b == src.n_row):
                raise RuntimeError(f"{src.ms}: a band read in storage order must be one "
                                   "block; this is a hitops bug")
            t = np.sort(t)   # the band's only block: its summaries need the times in order
        elif t.size and (np.any(t[1:] < t[:-1]) or t[0] < band.last_time):
            # dask-ms sorted the group by TIME (open_groups); anything else is a changed table
            raise TimeChangedError(src.ms)
        if t.size:
            band.last_time = float(t[-1])
        band.ordered_times.add(*distinct_counts(t))   # one pass: the block is in time order
    key = meta["ANTENNA1"].astype(np.int64) * src.n_ant + meta["ANTENNA2"]
    if key.size and (key.min() < 0 or key.max() >= band.pair_present.size):
        raise MeasurementSetError(f"{src.ms}: ANTENNA1/ANTENNA2 hold indices outside the "
                                  f"ANTENNA table ({src.n_ant} rows); the set is damaged")
    band.pair_present |= np.bincount(key, minlength=band.pair_present.size) > 0
    if band.pair_key is not None:
        band.pair_key[a:b] = key
        last = np.flatnonzero(np.concatenate([t[1:] != t[:-1], [True]])) if t.size else []
        band.time_scans.append((t[last], np.asarray(meta["SCAN_NUMBER"])[last]))
    band.scans.append(distinct_ints(meta["SCAN_NUMBER"]))
    iv = np.asarray(meta["INTERVAL"], dtype=np.float64)
    iv = iv[np.isfinite(iv) & (iv > 0)]
    if iv.size:
        band.min_interval = min(band.min_interval, float(iv.min()))


def _add_times(known, known_counts, times):
    """Distinct times and rows per time, with a block of times in any order added.

    A block of a baseline-major table in storage order holds parts of a few baselines'
    tracks, whose times are mostly known after the first: those are counted where the
    list has them (a linear lookup of ascending runs), and only the new ones sorted.
    """
    at = lookup_sorted(times, known)
    new = at < 0
    counts = known_counts + np.bincount(at[~new], minlength=known.size).astype(np.int64)
    if not new.any():
        return known, counts
    values, new_counts = np.unique(times[new], return_counts=True)
    return _merge_time_counts(known, counts, values, new_counts.astype(np.int64))


def _merge_time_counts(known, known_counts, values, counts):
    """Distinct times and rows per time, merged block by block.

    The merged list stays n_time long: a baseline-major table has nearly every
    time in every block, so keeping each block's own list would cost ~n_row.
    """
    if values.size and (known.size == 0 or values[0] >= known[-1]):
        # a block in time order after the ones before (a time-ordered band: every block
        # but the first): appended, the one time a block boundary may cut shared; a sort
        # of all times so far per block cost 0.6 s at 10^7 rows
        shared = bool(known.size) and values[0] == known[-1]
        merged_counts = np.concatenate([known_counts, counts[int(shared):]]).astype(np.int64)
        if shared:
            merged_counts[known.size - 1] += counts[0]
        return np.concatenate([known, values[int(shared):]]), merged_counts
    at = np.searchsorted(known, values)
    if known.size and at[-1] < known.size and np.array_equal(known[at], values):
        # every time of the block was seen before (baseline-major tables after the
        # first baseline): add the counts in place of a new sort
        return known, known_counts + np.bincount(at, weights=counts,
                                                 minlength=known.size).astype(np.int64)
    merged, inverse = np.unique(np.concatenate([known, values]), return_inverse=True)
    return merged, np.bincount(inverse, weights=np.concatenate([known_counts, counts]),
                               minlength=merged.size).astype(np.int64)
