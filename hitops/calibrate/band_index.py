"""Stage 4d, first pass: what calibrate keeps of each band's rows, without keeping the rows.

:func:`index_bands` reads the per-row metadata (:data:`INDEX_COLUMNS`) in
blocks of at most ``block_rows`` rows and fills one :class:`BandIndex` per band
with summaries (distinct times and their row counts, antenna pairs, scans,
smallest INTERVAL), and for a band in time order each row's antenna pair (two
bytes per row), so the checks of every chunk need not read the metadata again
(:meth:`hitops.calibrate.chunks.ChunkMatch.check`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..errors import MeasurementSetError
from ..io import read as msio
from ..io.match import distinct_counts, distinct_ints

#: per-row columns read in the first (index) pass
INDEX_COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "INTERVAL", "FLAG_ROW"]
#: per-row columns a chunk needs
ROW_COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "FLAG_ROW"]


@dataclass
class BandIndex:
    """Summary of one band's (field, spectral window) group.

    ``ds`` is the group's dask-ms dataset in time order (:func:`hitops.io.read.open_groups`),
    so the rows of any time range are one contiguous slice of it.  Per row only
    ``pair_key`` is kept (a band in time order read in several blocks).
    """

    ms: str
    ds: object
    n_row: int
    n_ant: int
    key: tuple = (0, 0)                   # (FIELD_ID, DATA_DESC_ID) of the group
    time_ordered: bool = False            # stored in time order: no sort when reopened
    ds_in_time_order: bool = True         # False: read whole in one chunk, storage order
    last_time: float = -np.inf
    unique_time: np.ndarray = None        # sorted distinct TIME values
    time_rows: np.ndarray = None          # rows at each distinct TIME value
    row_start: np.ndarray = None          # first row (dataset position) of each distinct TIME
    pair_present: np.ndarray = None       # (n_ant * n_ant,) ANTENNA1 * n_ant + ANTENNA2 used
    scans: np.ndarray = None
    min_interval: float = np.inf
    whole: Optional[Dict[str, np.ndarray]] = None   # every row's metadata, when one block
    pair_key: Optional[np.ndarray] = None   # per row: ANTENNA1 * n_ant + ANTENNA2 (see index_bands)
    time_scan: Optional[np.ndarray] = None  # SCAN_NUMBER of the last row at each distinct TIME

    def rows_in(self, lo: float, hi: float) -> slice:
        """Dataset positions of the rows with lo <= TIME < hi (they follow each other)."""
        if not self.ds_in_time_order:
            raise RuntimeError(f"{self.ms}: a part of the track was asked of a band read in "
                               "storage order (one chunk only); this is a hitops bug")
        u0, u1 = np.searchsorted(self.unique_time, [lo, hi])
        return slice(int(self.row_start[u0]), int(self.row_start[u1]))


def index_bands(bands: List[BandIndex], columns: List[List[str]], block_rows: int,
                scheduler=None) -> None:
    """Fill each :class:`BandIndex` from blocks of at most ``block_rows`` rows.

    Blocks of both bands are read in one dask call (the tables concurrently),
    as slices of each band's dataset (whose dask blocks are ``block_rows``
    long).  A band that fits in one block keeps that block's metadata in
    ``whole`` (it is bounded by ``block_rows`` and saves reading it again).  A
    band in time order read in several blocks keeps each row's antenna pair
    (``pair_key``: 2 bytes per row up to 256 stations) and the scan at each
    time (``time_scan``): with the rows' times, which follow from their
    positions, that is all the checks of every chunk need, so they read
    nothing again (:meth:`hitops.calibrate.chunks.ChunkMatch.check`).
    """
    for band in bands:
        band.pair_present = np.zeros(band.n_ant * band.n_ant, dtype=bool)
        if band.ds_in_time_order and band.n_row > block_rows:
            key_type = np.uint16 if band.n_ant * band.n_ant <= 1 << 16 else np.uint32
            band.pair_key = np.empty(band.n_row, dtype=key_type)
    parts = {id(b): {"unique": np.zeros(0), "counts": np.zeros(0, np.int64), "scans": [],
                     "time_scans": []} for b in bands}
    n_blocks = max(-(-b.n_row // block_rows) for b in bands)
    for k in range(n_blocks):
        requests, which = [], []
        for band, cols in zip(bands, columns):
            a, b = k * block_rows, min(band.n_row, (k + 1) * block_rows)
            if a < b:
                one_block = a == 0 and b == band.n_row
                requests.append((band.ds, list(cols) + (["ROWID"] if one_block else []),
                                 slice(a, b)))
                which.append((band, a, b))
        for (band, a, b), meta in zip(which, msio.compute_columns(requests, scheduler)):
            _summarise_block(band, a, b, meta, parts[id(band)])
            if a == 0 and b == band.n_row:
                band.whole = {c: meta[c] for c in ROW_COLUMNS + ["ROWID"]}
    for band in bands:
        p = parts[id(band)]
        band.unique_time, band.time_rows = p["unique"], p["counts"]
        band.scans = np.unique(np.concatenate(p["scans"]))
        band.row_start = np.concatenate([[0], np.cumsum(band.time_rows)])
        if band.pair_key is not None:
            # blocks in time order: a time cut by a block boundary takes the later block's
            band.time_scan = np.empty(band.unique_time.size, dtype=np.int64)
            for times, scans in p["time_scans"]:
                band.time_scan[np.searchsorted(band.unique_time, times)] = scans


def _summarise_block(band: BandIndex, a: int, b: int, meta: Dict[str, np.ndarray], p) -> None:
    t = np.asarray(meta["TIME"], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        row = int(meta["ROWID"][bad]) if "ROWID" in meta else a + bad
        raise MeasurementSetError(f"{band.ms}: TIME of row {row} is {t[bad]}; rows without "
                                  "a valid time cannot be matched: remove them (CASA split "
                                  "with a time range) or repair the TIME column")
    if not band.ds_in_time_order:
        if not (a == 0 and b == band.n_row):
            raise RuntimeError(f"{band.ms}: a band read in storage order must be one block; "
                               "this is a hitops bug")
        t = np.sort(t)   # the band's only block: its summaries need the times in order
    elif t.size and (np.any(t[1:] < t[:-1]) or t[0] < band.last_time):
        # dask-ms sorted the group by TIME (open_groups); anything else is a changed table
        raise MeasurementSetError(f"{band.ms}: TIME changed while it was being read; run "
                                  "again when nothing else writes to the set")
    if t.size:
        band.last_time = float(t[-1])
    values, counts = distinct_counts(t)   # one pass: the block is in time order
    p["unique"], p["counts"] = _merge_time_counts(p["unique"], p["counts"], values, counts)
    key = meta["ANTENNA1"].astype(np.int64) * band.n_ant + meta["ANTENNA2"]
    if key.size and (key.min() < 0 or key.max() >= band.pair_present.size):
        raise MeasurementSetError(f"{band.ms}: ANTENNA1/ANTENNA2 hold indices outside the "
                                  f"ANTENNA table ({band.n_ant} rows); the set is damaged")
    band.pair_present |= np.bincount(key, minlength=band.pair_present.size) > 0
    if band.pair_key is not None:
        band.pair_key[a:b] = key
        last = np.flatnonzero(np.concatenate([t[1:] != t[:-1], [True]])) if t.size else []
        p["time_scans"].append((t[last], np.asarray(meta["SCAN_NUMBER"])[last]))
    p["scans"].append(distinct_ints(meta["SCAN_NUMBER"]))
    iv = np.asarray(meta["INTERVAL"], dtype=np.float64)
    iv = iv[np.isfinite(iv) & (iv > 0)]
    if iv.size:
        band.min_interval = min(band.min_interval, float(iv.min()))


def _merge_time_counts(known, known_counts, values, counts):
    """Distinct times and rows per time, merged block by block.

    The merged list stays n_time long: a baseline-major table has nearly every
    time in every block, so keeping each block's own list would cost ~n_row.
    """
    at = np.searchsorted(known, values)
    if known.size and at[-1] < known.size and np.array_equal(known[at], values):
        # every time of the block was seen before (baseline-major tables after the
        # first baseline): add the counts in place of a new sort
        return known, known_counts + np.bincount(at, weights=counts,
                                                 minlength=known.size).astype(np.int64)
    merged, inverse = np.unique(np.concatenate([known, values]), return_inverse=True)
    return merged, np.bincount(inverse, weights=np.concatenate([known_counts, counts]),
                               minlength=merged.size).astype(np.int64)
