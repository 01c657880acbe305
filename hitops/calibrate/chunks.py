"""Matching the two bands chunk by chunk, so memory is bounded by ``--chunk-rows``.

Matching every row at once would hold each row's metadata and index
(~120 bytes per row and band, measured); here what stays per row is each row's
antenna pair (2 bytes per row and band, for a band read in several blocks) and
what dask-ms keeps for the datasets it opens.  The rest is per block of rows or
per time chunk:

1. :func:`hitops.calibrate.band_index.index_bands` reads the per-row metadata
   in blocks of at most ``block_rows`` rows and keeps small summaries (distinct
   times, antenna pairs, scans, smallest INTERVAL) and the rows' pair keys;
2. :class:`GroupMatch` builds the union time axis, the target baselines and
   the reference-pair tables from those summaries (sizes n_time, n_bl,
   n_ant^2);
3. :meth:`GroupMatch.check` takes each time chunk's baselines and times (from
   the pair keys and the rows' positions, or read again when they were not
   kept), checks for duplicate cells, counts matched rows and finds the scan
   of each time, all before anything is written, and returns them as a
   :class:`MatchCheck` (the match itself is not changed);
4. :meth:`GroupMatch.row_numbers` and :meth:`GroupMatch.rows_from_index` (from the
   pair keys) or :meth:`GroupMatch.index_rows` (from metadata read again) give a
   chunk's row numbers, baseline and time indices when it is processed.

The matching rules are those of :mod:`hitops.io.match` (same tolerance, same
station and correlation maps), so the result equals the whole-track match.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import MeasurementSetError, TimeChangedError
from ..io import read as msio
from ..io.layout import GridShape, unique_times
from ..io.match import correlation_map, pair_antennas, pairing_table
from ..io.stations import Stations
from ..io.ms_create import CORR_NAMES
from ..kernels.cells import band_cells, count_marked, mark_cells
from ..tracking.grid import ScanAxis
from .band_index import ROW_COLUMNS, BandIndex


@dataclass
class ChunkRows:
    """One band's rows of a time chunk on the (baseline, time) grid."""

    rows: np.ndarray        # row numbers (ROWID) in the table, in the dataset's time order
    bl: np.ndarray          # baseline index (-1: reference pair without target baseline)
    time: np.ndarray        # union time index
    swapped: np.ndarray     # reference only: antenna order reversed
    flag_row: np.ndarray
    scan: np.ndarray


@dataclass(frozen=True)
class MatchCheck:
    """What :meth:`GroupMatch.check` found in every chunk (nothing of it is kept on the match)."""

    n_matched: int                  # target rows with a reference row in their cell
    n_ref_unused: int               # reference rows without a target row in their cell
    scans: ScanAxis                 # from SCAN_NUMBER (the target's where it has a row)
    # (target, reference) rows of a one-chunk run, so its read need not index them again
    first_chunk: Optional[Tuple[ChunkRows, ChunkRows]]


class GroupMatch(GridShape):
    """The two bands' common grid (times, baselines) without per-row arrays.

    Built whole here, then only read: the common grid (times, ant1, ant2,
    baseline_names, corr_map, corr_names, scan_numbers, tolerance) and each
    band's rows of a time chunk.  :meth:`check` returns what it counts
    (:class:`MatchCheck`); :meth:`with_datasets` gives a copy reading through
    other datasets.
    """

    def __init__(self, ref: BandIndex, tgt: BandIndex, ref_stations: Stations,
                 tgt_stations: Stations, ref_corr, tgt_corr, antenna_map, tolerance=None,
                 datasets: Dict[str, object] = None):
        self.ref, self.tgt = ref, tgt
        # "ref"/"tgt" -> the dask-ms dataset the band is read through (the match's own;
        # chunk_datasets makes others for with_datasets), the bands' indexes are only read
        self.datasets: Dict[str, object] = dict(datasets or {})
        tgt_names = tgt_stations.codes
        n_ant_t, n_ant_r = tgt_stations.n_ant, ref_stations.n_ant
        pairs = np.flatnonzero(tgt.pair_present)
        bl_a1, bl_a2 = pairs // n_ant_t, pairs % n_ant_t
        # stations paired by code (never by antenna index); see hitops/io/match.py
        ref_to_tgt = pair_antennas(ref_stations, tgt_stations, antenna_map, bl_a1, bl_a2)
        self.pairing = pairing_table(ref_stations, tgt_stations, ref_to_tgt)
        self.corr_map = correlation_map(ref_corr, tgt_corr)
        self.corr_names = [CORR_NAMES.get(int(c), str(c)) for c in tgt_corr]
        if not np.any(self.corr_map[0] >= 0):
            raise MeasurementSetError(
                f"no correlation of {tgt.ms} ({', '.join(self.corr_names)}) exists in {ref.ms} "
                f"({', '.join(CORR_NAMES.get(int(c), str(c)) for c in ref_corr)}); "
                "both bands need the same polarisation products")
        if tolerance is None:
            smallest = min(ref.min_interval, tgt.min_interval)
            tolerance = 0.5 * smallest if np.isfinite(smallest) else 1e-3
        self.tolerance = float(tolerance)
        # baseline of each target pair, and of each reference pair (either order)
        self.tgt_pair_bl = np.full(n_ant_t * n_ant_t, -1, dtype=np.int32)
        self.tgt_pair_bl[pairs] = np.arange(pairs.size)
        ra1, ra2 = np.divmod(np.arange(n_ant_r * n_ant_r), n_ant_r)
        m1, m2 = ref_to_tgt[ra1], ref_to_tgt[ra2]
        ok = (m1 >= 0) & (m2 >= 0)
        direct = np.where(ok, self.tgt_pair_bl[np.where(ok, m1 * n_ant_t + m2, 0)], -1)
        reverse = np.where(ok, self.tgt_pair_bl[np.where(ok, m2 * n_ant_t + m1, 0)], -1)
        self.ref_pair_bl = np.where(direct >= 0, direct, reverse).astype(np.int32)
        self.ref_pair_swapped = (direct < 0) & (reverse >= 0)
        self.ant1, self.ant2 = bl_a1, bl_a2
        self.baseline_names = [f"{tgt_names[a]}-{tgt_names[b]}" for a, b in zip(bl_a1, bl_a2)]
        # union time axis from the distinct times of both bands
        self.times, group = unique_times(np.concatenate([tgt.unique_time, ref.unique_time]),
                                         self.tolerance)
        self.tgt_group = group[:tgt.unique_time.size]
        self.ref_group = group[tgt.unique_time.size:]
        # distinct SCAN_NUMBER values of both bands
        self.scan_numbers = np.union1d(tgt.scans, ref.scans)

    def _time_range(self, band: BandIndex, group: np.ndarray, t0: int, t1: int):
        """TIME values [lo, hi) of the band's rows whose union time index is in [t0, t1)."""
        u0, u1 = np.searchsorted(group, [t0, t1])
        lo = band.unique_time[u0] if u0 < group.size else np.inf
        hi = band.unique_time[u1] if u1 < group.size else np.inf
        return lo, hi

    def _side(self, which: str):
        """("tgt" or "ref") -> that band's index and its distinct times' union time indices."""
        return (self.tgt, self.tgt_group) if which == "tgt" else (self.ref, self.ref_group)

    def row_numbers(self, which: str, t0: int, t1: int) -> slice:
        """Dataset positions of a band's rows whose union time index is in [t0, t1)."""
        band, group = self._side(which)
        if t0 <= 0 and t1 >= self.n_time:
            return slice(0, band.n_row)
        return band.rows_in(*self._time_range(band, group, t0, t1))

    def with_datasets(self, datasets: Dict[str, object]) -> "GroupMatch":
        """A copy of this match reading the bands named in ``datasets`` ("tgt", "ref")
        through those datasets (the grid's arrays are shared, not copied)."""
        other = copy.copy(self)
        other.datasets = {**self.datasets, **datasets}
        return other

    def chunk_datasets(self, bounds: List[int], columns: Dict[str, List[str]],
                       split: Dict[str, int] = None) -> Dict[str, object]:
        """For each band named in ``columns`` ("tgt", "ref") whose dataset is not the
        table itself, a dataset whose dask blocks are the time chunks, so each chunk's
        read is exactly its rows (for :meth:`with_datasets`).

        ``split``: blocks per chunk for a band read with context beyond its chunks
        (the robust trackers' reference band): a read then touches at most a small
        block on either side instead of whole neighbouring chunks.
        """
        split = split or {}
        chunked = {}
        for which, cols in columns.items():
            band = self.tgt if which == "tgt" else self.ref
            sizes = []
            for t0, t1 in zip(bounds[:-1], bounds[1:]):
                span = self.row_numbers(which, t0, t1)
                n, parts = span.stop - span.start, max(1, int(split.get(which, 1)))
                sizes.extend(p for p in np.diff(np.linspace(0, n, parts + 1).astype(np.int64))
                             if p > 0)
            if len(sizes) > 1 and not isinstance(self.datasets[which], msio.StorageRows):
                datasets = msio.open_groups(band.ms, [c for c in dict.fromkeys(cols) if c != "ROWID"],
                                            tuple(sizes), band.time_ordered, only=band.key)
                # the band's only dataset from then on: the first one (and the row order
                # dask-ms keeps for it, 8 bytes per row) can go
                chunked[which] = datasets[band.key]
        return chunked

    def time_counts(self) -> np.ndarray:
        """Rows of both bands per union time (for cutting chunks)."""
        return (np.bincount(self.tgt_group, weights=self.tgt.time_rows, minlength=self.n_time)
                + np.bincount(self.ref_group, weights=self.ref.time_rows,
                              minlength=self.n_time)).astype(np.int64)

    def chunk_request(self, which: str, rows: slice, columns: List[str]):
        """A :func:`hitops.io.read.compute_columns` request for a band's ``columns`` at ``rows``."""
        return (self.datasets[which], list(columns), rows)

    def read_meta(self, which, rows: slice, columns, scheduler=None):
        band = self.tgt if which == "tgt" else self.ref
        if band.whole is not None:
            return {c: band.whole[c][rows] for c in columns}
        return msio.compute_columns([(self.datasets[which], columns, rows)], scheduler)[0]

    def index_rows(self, which, meta) -> ChunkRows:
        band, group = self._side(which)
        from ..kernels.sorted_runs import lookup_sorted

        # every TIME is one of the band's distinct times (read from the same column)
        at = lookup_sorted(np.ascontiguousarray(meta["TIME"], dtype=np.float64), band.unique_time)
        if at.size and at.min() < 0:
            raise TimeChangedError(band.ms)
        key = meta["ANTENNA1"].astype(np.int64) * band.n_ant + meta["ANTENNA2"]
        return self._on_grid(which, key, group.astype(np.int32)[at], meta.get("SCAN_NUMBER"),
                             rows=meta.get("ROWID"), flag_row=meta.get("FLAG_ROW"))

    def rows_from_index(self, which: str, rows: slice, meta) -> ChunkRows:
        """A chunk's :class:`ChunkRows` of a band whose index pass kept its pair keys:
        each row's antenna pair and time from its position, and the TIME, ROWID and
        FLAG_ROW in ``meta`` read with its data.  The index pass read ANTENNA1 and
        ANTENNA2 of these very positions, so the chunk's read need not, nor look each
        TIME up: TIME is only compared with the times the index holds for these
        positions (the same refusal as :meth:`index_rows` when it changed)."""
        band, group = self._side(which)
        span = band.times_of(rows)
        at = np.repeat(np.arange(span.start, span.stop), band.time_rows[span])
        if not np.array_equal(np.asarray(meta["TIME"], dtype=np.float64),
                              band.unique_time[at]):
            raise TimeChangedError(band.ms)
        found = self._on_grid(which, band.pair_key[rows], group[at].astype(np.int32), None)
        return ChunkRows(rows=meta["ROWID"], bl=found.bl, time=found.time,
                         swapped=found.swapped, flag_row=meta["FLAG_ROW"], scan=None)

    def _on_grid(self, which: str, key, time, scan, rows=None, flag_row=None) -> ChunkRows:
        """:class:`ChunkRows` of a band's rows from their antenna-pair keys and union times."""
        if which == "tgt":
            bl, swapped = self.tgt_pair_bl[key], None
        else:
            bl, swapped = self.ref_pair_bl[key], self.ref_pair_swapped[key]
        return ChunkRows(rows=rows, bl=bl, time=time, swapped=swapped, flag_row=flag_row,
                         scan=scan)

    def check(self, bounds: List[int], scheduler=None, keep_single: bool = True) -> MatchCheck:
        """Check every chunk's cells, count matches, find each time's scan (before any write).

        The result's ``first_chunk`` holds the chunk's (tgt, ref) :class:`ChunkRows`
        when there is one chunk and ``keep_single`` (so it is not computed twice).
        """
        kept = None
        n_matched = n_ref_unused = 0
        scan_of_time = np.zeros(self.times.size, dtype=np.int64)
        cols = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER"]
        from_index = self.tgt.pair_key is not None and self.ref.pair_key is not None
        for t0, t1 in zip(bounds[:-1], bounds[1:]):
            t_rows = self.row_numbers("tgt", t0, t1)
            r_rows = self.row_numbers("ref", t0, t1)
            if from_index:   # nothing to read (hitops/calibrate/band_index.py)
                for which, rows in (("ref", r_rows), ("tgt", t_rows)):
                    self._index_scans(which, rows, scan_of_time)
                matched, unused = self._check_cells(self._index_cells("tgt", t_rows, t0, t1),
                                                    self._index_cells("ref", r_rows, t0, t1),
                                                    r_rows.stop - r_rows.start, t0, t1)
                n_matched, n_ref_unused = n_matched + matched, n_ref_unused + unused
                continue
            if self.tgt.whole is not None and self.ref.whole is not None:
                t_meta = self.read_meta("tgt", t_rows, ROW_COLUMNS + ["ROWID"])
                r_meta = self.read_meta("ref", r_rows, ROW_COLUMNS + ["ROWID"])
            else:
                t_meta, r_meta = msio.compute_columns(
                    [self.chunk_request("tgt", t_rows, cols),
                     self.chunk_request("ref", r_rows, cols)], scheduler)
            tgt = self.index_rows("tgt", t_meta)
            ref = self.index_rows("ref", r_meta)
            matched, unused = self._check_chunk(tgt, ref, t0, t1, scan_of_time)
            n_matched, n_ref_unused = n_matched + matched, n_ref_unused + unused
            if len(bounds) == 2 and keep_single and "FLAG_ROW" in t_meta:
                kept = (tgt, ref)
        if n_matched == 0:
            raise MeasurementSetError(
                f"no row of {self.tgt.ms} has a counterpart in {self.ref.ms} at the same time "
                f"(tolerance {self.tolerance:g} s) and station pair: target times "
                f"{self.tgt.unique_time[0]:.1f}..{self.tgt.unique_time[-1]:.1f}, reference "
                f"times {self.ref.unique_time[0]:.1f}..{self.ref.unique_time[-1]:.1f} "
                "(MJD seconds); check that the two sets cover the same observation")
        return MatchCheck(n_matched=n_matched, n_ref_unused=n_ref_unused,
                          scans=ScanAxis(self.scan_numbers, scan_of_time), first_chunk=kept)

    def _check_chunk(self, tgt: ChunkRows, ref: ChunkRows, t0: int, t1: int,
                     scan_of_time: np.ndarray) -> Tuple[int, int]:
        """(matched target rows, unused reference rows) of one chunk read again; sets the
        chunk's times in ``scan_of_time`` (check's own array, filled chunk by chunk)."""
        n_t = t1 - t0
        # target's SCAN_NUMBER where the target has a row at that time, else the reference's
        scan_of_time[ref.time] = np.searchsorted(self.scan_numbers, ref.scan)
        scan_of_time[tgt.time] = np.searchsorted(self.scan_numbers, tgt.scan)
        t_cells = tgt.bl.astype(np.int64) * n_t + (tgt.time - t0)
        r_cells = np.where(ref.bl >= 0, ref.bl.astype(np.int64) * n_t + (ref.time - t0), -1)
        return self._check_cells(t_cells, r_cells, ref.bl.size, t0, t1)

    def _index_cells(self, which: str, rows: slice, t0: int, t1: int) -> np.ndarray:
        """Each row's cell (-1: no baseline) from the index pass's pair keys."""
        band, group = self._side(which)
        span = band.times_of(rows)
        pair_bl = self.tgt_pair_bl if which == "tgt" else self.ref_pair_bl
        return band_cells(band.pair_key[rows], pair_bl, band.time_rows[span], group[span],
                          t0, t1 - t0)

    def _index_scans(self, which: str, rows: slice, scan_of_time: np.ndarray) -> None:
        """Each distinct time's scan (that of its last row) into ``scan_of_time``."""
        band, group = self._side(which)
        span = band.times_of(rows)
        scan_of_time[group[span]] = np.searchsorted(self.scan_numbers, band.time_scan[span])

    def _check_cells(self, t_cells: np.ndarray, r_cells: np.ndarray, n_ref_rows: int,
                     t0: int, t1: int) -> Tuple[int, int]:
        """(matched target rows, unused reference rows) from the rows' cells (-1: a
        reference pair without a target baseline); two rows in one cell are refused."""
        n_t = t1 - t0
        has_tgt, shared = mark_cells(t_cells, self.n_bl * n_t)
        if shared:
            self._raise_duplicate(t_cells, n_t, t0, self.tgt.ms)
        has_ref, shared = mark_cells(r_cells, self.n_bl * n_t)
        if shared:
            self._raise_duplicate(r_cells[r_cells >= 0], n_t, t0, self.ref.ms)
        return (int(count_marked(t_cells, has_ref)),
                int(n_ref_rows - count_marked(r_cells, has_tgt)))

    def _raise_duplicate(self, cells, n_t, t0, ms):
        counts = np.bincount(cells, minlength=self.n_bl * n_t)
        dup = np.flatnonzero(counts > 1)
        b, t = divmod(int(dup[0]), n_t)
        raise MeasurementSetError(
            f"{ms}: {int((counts[dup] - 1).sum())} rows share a (baseline, time) cell with "
            f"another row, e.g. {self.baseline_names[b]} at TIME {self.times[t0 + t]:.3f}; the "
            "data mix several fields, spectral windows or sub-arrays, or the time tolerance is "
            "too large: split them (e.g. CASA split by field/spw) and run on each part")
