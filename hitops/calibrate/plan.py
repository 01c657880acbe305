"""Stage 3 of ``hitops calibrate``: the plan, built once from both bands' metadata.

A :class:`RunPlan` holds what the whole run shares (options, columns, chunk
size, the open dask-ms datasets); a :class:`GroupPlan` holds one (field,
spectral window) pair of groups: the matched stations, correlations and times
(:class:`hitops.calibrate.chunks.GroupMatch`), the grid and tracking scans the
trackers run on (:class:`hitops.tracking.grid.TrackGrid`), the chunk bounds, R
and its split r + eps, and the resolved tracking setup.  Every chunk's cells
are checked here, so a plan that builds is one the pipeline can write.  Each
plan is built whole, then only read.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import InputError, MeasurementSetError
from ..io import read as msio
from ..io.match import parse_antenna_map
from ..io.metadata import SetMetadata, read_metadata
from ..io.stations import Stations, stations_of
from ..tracking.grid import ScanAxis, TrackGrid
from ..tracking.options import TrackingSetup
from .band_index import INDEX_COLUMNS, ROW_COLUMNS, BandSource, index_bands
from .chunks import GroupMatch, ChunkRows, MatchCheck
from .channels import ChannelPlan, channel_plan, check_channel_counts
from .groups import GroupPair, describe_groups, pair_groups
from .inputs import CalibrateOptions, Columns

log = logging.getLogger("hitops.calibrate")


@dataclass
class GroupPlan:
    """One (field, spectral window) group pair, matched and checked."""

    pair: GroupPair
    label: str                      # '' when the sets hold one group
    match: GroupMatch
    grid: TrackGrid                 # the match's baselines and times, the tracking scans
    bounds: List[int]               # chunk k covers union times [bounds[k], bounds[k+1])
    # the checks' (target, reference) rows of a one-chunk run, reused by the read
    first_chunk: Optional[Tuple[ChunkRows, ChunkRows]]
    ratio: float                    # R = nu_target / nu_reference
    r: int
    eps: float                      # R = r + eps
    ratio_source: str
    # the smooth/antenna trackers' resolved parameters; the count tracker has none (None)
    tracking: Optional[TrackingSetup]
    n_target_rows: int
    n_matched: int                  # target rows with a reference row (GroupMatch.check)
    n_ref_unused: int               # reference rows without a target row
    antenna_names: List[str]        # station codes of the target set, by antenna index
    # several channels: one ratio per target channel (hitops/calibrate/channels.py)
    channels: Optional[ChannelPlan] = None

    @property
    def n_chunks(self) -> int:
        return len(self.bounds) - 1

    @property
    def n_corr(self) -> int:
        return len(self.match.corr_names)

    @property
    def reads_stores(self) -> bool:
        """Both bands' groups are partitions of MSv4 processing sets (on a cluster, its
        workers then read and write each chunk: hitops/calibrate/worker_chunks.py)."""
        from ..io.msv4.group_rows import PartitionSource

        return all(isinstance(self.match.datasets[band], PartitionSource)
                   for band in ("ref", "tgt"))


@dataclass
class RunPlan:
    """What every group of a run shares, and the groups."""

    opts: CalibrateOptions          # the schema's typed options (hitops/options.py)
    methods: List[str]
    outputs: Dict[str, str]         # method -> column
    ref_ms: str
    target_ms: str
    columns: Columns
    chunk_rows: int
    budget: int                     # --memory-budget in bytes (auto resolved once)
    groups: List[GroupPlan] = field(default_factory=list)
    timings: Dict[str, float] = field(default_factory=dict)
    #: each set's subtables, read once (hitops/io/metadata.py) for every later stage
    ref_meta: Optional[SetMetadata] = None
    tgt_meta: Optional[SetMetadata] = None


def split_ratio(ratio: float):
    """(r, eps) with R = r + eps; R within 1e-9 of an integer counts as that integer."""
    nearest = round(ratio)
    if abs(ratio - nearest) < 1e-9:
        return int(nearest), 0.0
    r = math.floor(ratio)
    return int(r), float(ratio - r)


def chunk_bounds(per_time: np.ndarray, chunk_rows: int) -> List[int]:
    """Time-index boundaries so that each chunk holds at most ~2 * chunk_rows rows of both
    bands (``per_time``: rows of both bands at each union time; a time is never split)."""
    n_time = per_time.size
    cum = np.cumsum(per_time)
    bounds = [0]
    while bounds[-1] < n_time:
        start_count = cum[bounds[-1] - 1] if bounds[-1] > 0 else 0
        stop = int(np.searchsorted(cum, start_count + 2 * chunk_rows, side="right"))
        bounds.append(min(max(stop, bounds[-1] + 1), n_time))
    return bounds


def rows_from_budget(budget: int, ref_ms: str, target_ms: str, columns: Columns,
                     n_methods: int, time_ordered: bool, strict: bool,
                     local: bool = False, stores: Optional[Dict[str, Dict]] = None,
                     tracker: str = "count", n_ant: int = 0) -> int:
    """Rows per time chunk that keep the run within ``budget`` bytes (hitops/calibrate/memory.py).

    ``time_ordered``: both sets are stored in time order; ``strict``: the budget was
    given (not the default), so a budget too small is an error; ``local``: no cluster,
    the sets are read without dask-ms (hitops/io/read.py, open_for_reading), and neither
    set mixes fields or windows (those are still read through dask-ms's datasets);
    ``stores``: the processing-set bands' groups, opened already (:func:`_open_stores`);
    ``tracker`` and ``n_ant``: the run's tracker and the target's stations (what the
    tracker holds, :func:`hitops.calibrate.memory.tracker_bytes`).
    """
    from .memory import min_chunk_rows, rows_for_budget, tracker_bytes
    from .output_msv4 import transaction_class

    n_rows, n_corr, n_chan, n_target = 0, 1, 1, 0
    for ms, column in ((ref_ms, columns.ref_data), (target_ms, columns.target_data)):
        rows, shape = _column_extent(ms, column, stores or {})
        n_rows += rows
        n_target = rows if ms == target_ms else n_target
        if rows:
            n_chan, n_corr = max(n_chan, int(shape[0])), max(n_corr, int(shape[-1]))
    rows = rows_for_budget(budget, n_rows, n_corr, n_chan, n_methods, time_ordered, strict,
                           local, writes_apart=transaction_class(target_ms).writes_apart,
                           tracker=tracker_bytes(tracker, n_corr, n_target, n_ant))
    if rows == min_chunk_rows(n_chan) and not strict:
        log.warning("the default memory budget (%.0f MB) cannot hold %d rows%s and a chunk: "
                    "chunks of %d rows; give --memory-budget or --chunk-rows to choose",
                    budget / 1e6, n_rows, "" if time_ordered or local else
                    " (a table not stored in time order: dask-ms sorts it and keeps the order)",
                    rows)
    log.info("memory budget %.0f MB: up to %d target rows per time chunk (--chunk-rows "
             "overrides)", budget / 1e6, rows)
    return rows


def _open_stores(read_columns: Dict[str, List[str]]) -> Dict[str, Dict]:
    """Each processing-set band's groups (store -> {(FIELD_ID, DATA_DESC_ID):
    PartitionSource}), opened once for the plan: opening one reads its presence array
    (80 MB per band at 10^7 rows), which the chunk size, the row counts and the run all
    take from.  A Measurement Set v2 is opened once the chunk size is known (how depends
    on it)."""
    from ..io.msv4.group_rows import open_partition_groups
    from ..io.msv4.store import is_processing_set

    return {ms: open_partition_groups(ms, cols) for ms, cols in read_columns.items()
            if is_processing_set(ms)}


def _column_extent(ms: str, column: str, stores: Dict[str, Dict]) -> Tuple[int, tuple]:
    """(rows, cell shape of ``column``) of a band, from its opened groups when it has them."""
    if ms not in stores:
        return msio.column_extent(ms, column)
    groups = list(stores[ms].values())
    return _row_count(ms, stores), groups[0].cell_shape(column) if groups else ()


def _row_count(ms: str, stores: Dict[str, Dict]) -> int:
    """Rows of a band, from its opened groups when it has them."""
    if ms not in stores:
        return msio.row_count(ms)
    return sum(g.n_rows for g in stores[ms].values())


def build_plan(opts: CalibrateOptions, methods: List[str], outputs: Dict[str, str], ref_ms: str,
               target_ms: str, columns: Columns, timings: Dict[str, float]) -> RunPlan:
    """Open both bands, pair their groups and plan each pair (nothing written yet)."""
    from .memory import parse_budget

    budget = parse_budget(opts.run.memory_budget)
    antenna_map = parse_antenna_map(opts.input.antenna_map)
    stage = time.perf_counter()
    # each set's subtables, read once for the run and passed down
    ref_meta, tgt_meta = read_metadata(ref_ms), read_metadata(target_ms)
    # a table stored in time order is read in that order; any other is sorted by dask-ms
    ordered = {ms: msio.is_time_ordered(ms) for ms in (ref_ms, target_ms)}
    read_columns = {ref_ms: list(dict.fromkeys(INDEX_COLUMNS + columns.ref + columns.snr)),
                    target_ms: list(dict.fromkeys(INDEX_COLUMNS + columns.tgt))}
    stores = _open_stores(read_columns)
    chunk_rows = int(opts.run.chunk_rows)
    if chunk_rows == 0:
        explicit = str(opts.run.memory_budget or "auto").strip().lower() != "auto"
        chunk_rows = rows_from_budget(budget, ref_ms, target_ms, columns, len(methods),
                                      all(ordered.values()), strict=explicit,
                                      # sets of several fields or windows are still read
                                      # through dask-ms's datasets
                                      local=not (opts.run.scheduler or ref_meta.has_groups()
                                                 or tgt_meta.has_groups()),
                                      stores=stores, tracker=opts.tracking.tracker,
                                      n_ant=len(tgt_meta.antennas.names))
    # dask row chunks of chunk_rows rows: the metadata blocks of the first pass are
    # slices of these datasets (no dataset per block); a field/spectral-window group is a
    # dataset of its own, so FIELD_ID and DATA_DESC_ID are not read per row
    io_rows = min(chunk_rows, 1 << 21)
    # sets read whole in one chunk need no time order either: dask-ms's sort (~0.45 s per
    # 10^6 rows) and writing rows out of storage order are skipped
    n_rows = {ms: _row_count(ms, stores) for ms in (ref_ms, target_ms)}
    one_chunk = sum(n_rows.values()) <= 2 * chunk_rows and max(n_rows.values()) <= chunk_rows
    in_time_order = {ms: not (one_chunk and not ordered[ms]) for ms in ordered}
    # one chunk on this process: a set of one group is read by python-casacore directly
    direct = one_chunk and not opts.run.scheduler
    ref_groups, tgt_groups = (
        stores[ms] if ms in stores else
        msio.open_for_reading(ms, read_columns[ms], io_rows, ordered[ms] or one_chunk, direct,
                              local=not opts.run.scheduler, mixed=meta.has_groups())
        for ms, meta in ((ref_ms, ref_meta), (target_ms, tgt_meta)))
    timings["open"] = time.perf_counter() - stage
    ref_role, tgt_role = "reference-band Measurement Set", "target-band Measurement Set"
    ref_stations = stations_of(ref_ms, ref_meta.antennas, ref_role)
    tgt_stations = stations_of(target_ms, tgt_meta.antennas, tgt_role)
    pairs = pair_groups(ref_ms, target_ms, describe_groups(ref_meta, ref_groups, ref_role),
                        describe_groups(tgt_meta, tgt_groups, tgt_role))
    if len(pairs) > 1:
        log.info("%d (field, spectral window) groups calibrated one by one: %s", len(pairs),
                 "; ".join(p.label for p in pairs))
    run = RunPlan(opts=opts, methods=methods, outputs=outputs, ref_ms=ref_ms,
                  target_ms=target_ms, columns=columns, chunk_rows=chunk_rows, budget=budget,
                  timings=timings, ref_meta=ref_meta, tgt_meta=tgt_meta)
    for pair in pairs:
        ref_band = _band(ref_ms, ref_groups, pair.ref.key, ref_stations.n_ant, ordered[ref_ms],
                         in_time_order[ref_ms])
        tgt_band = _band(target_ms, tgt_groups, pair.tgt.key, tgt_stations.n_ant,
                         ordered[target_ms], in_time_order[target_ms])
        run.groups.append(plan_group(run, pair, ref_band, tgt_band, ref_stations, tgt_stations,
                                     antenna_map, label=pair.label if len(pairs) > 1 else ""))
    if opts.output.caltable and len(pairs) > 1 and any(g.channels is None for g in run.groups):
        # a per-channel transfer's Fringe Jones table holds every window and field; the
        # single-ratio G Jones table holds one group
        raise InputError(f"--caltable {opts.output.caltable}: the sets hold {len(pairs)} field/"
                         "spectral-window groups and the G Jones table holds one; split them "
                         "(CASA split field=/spw=) and write one table per group")
    if opts.output.export_uvfits:
        _check_export_fields(opts.output.export_uvfits, target_ms, tgt_meta, tgt_groups, run)
    return run


def _check_export_fields(export: str, target_ms: str, tgt_meta, tgt_groups: Dict,
                         run: RunPlan) -> None:
    """--export-uvfits writes the whole target set, and a UVFITS file holds one field:
    checked here, before anything is written, since the export runs after the commit."""
    names = tgt_meta.fields.names
    held = sorted({names[field_id] if field_id < len(names) else str(field_id)
                   for field_id, _ in tgt_groups})
    if len(held) <= 1:
        return
    calibrated = sorted({g.pair.tgt.field for g in run.groups})
    if len(calibrated) > 1:
        what = (f"the run calibrates {len(calibrated)} fields of {target_ms} "
                f"({', '.join(calibrated)})")
    else:
        # a field without a partner in the reference band is left out of the run, but it
        # is still in the set the export would write
        what = (f"{target_ms} holds {len(held)} fields ({', '.join(held)}), of which the run "
                f"calibrates {calibrated[0]} only")
    raise InputError(f"--export-uvfits {export}: {what}, and a UVFITS file holds one field; "
                     "drop --export-uvfits and export each field from a set split by field "
                     "(CASA split field=...)")


def _band(ms: str, datasets: Dict, key, n_ant: int, time_ordered: bool,
          in_time_order: bool) -> BandSource:
    ds = datasets[key]
    return BandSource(ms=ms, ds=ds, n_ant=n_ant, n_row=int(ds.sizes["row"]), key=key,
                     time_ordered=time_ordered,
                     ds_in_time_order=in_time_order)


def _ratio(opts: CalibrateOptions, pair: GroupPair, label: str):
    """(R, r, eps, where R came from), logged."""
    ref_freq, tgt_freq = pair.ref.freq, pair.tgt.freq
    if opts.input.ratio is None:
        if not (ref_freq > 0 and tgt_freq > 0):
            raise MeasurementSetError(f"cannot take R from the spectral windows ({ref_freq} Hz, "
                                      f"{tgt_freq} Hz); pass --ratio")
        ratio = tgt_freq / ref_freq
        source = f"from the spectral windows: {tgt_freq / 1e9:.6g} GHz / {ref_freq / 1e9:.6g} GHz"
    else:
        ratio, source = float(opts.input.ratio), "from --ratio"
    r, eps = split_ratio(ratio)
    log.info("%sR = %.10g (%s): r = %d, eps = %.10g; a reference wrap moves CFPT by %.2f deg",
             f"{label}: " if label else "", ratio, source, r, eps,
             math.degrees(math.remainder(2 * math.pi * eps, 2 * math.pi)))
    if ratio < 1:
        log.warning("R = %.6g < 1: the target band is below the reference band; FPT scales "
                    "the reference phases down (PWC still applies, eps = R)", ratio)
    return ratio, r, eps, source


def plan_group(run: RunPlan, pair: GroupPair, ref_source: BandSource, tgt_source: BandSource,
               ref_stations: Stations, tgt_stations: Stations, antenna_map,
               label: str) -> GroupPlan:
    """Index, match and check one group pair before anything is written."""
    opts, columns, timings = run.opts, run.columns, run.timings
    if ref_source.n_row == 0 or tgt_source.n_row == 0:
        empty = run.ref_ms if ref_source.n_row == 0 else run.target_ms
        raise MeasurementSetError(f"{empty} has no rows ({pair.label}); nothing to calibrate")
    stage = time.perf_counter()
    # per-row metadata in blocks of at most chunk_rows rows; only summaries stay (and TIME
    # for tables not in time order), see hitops/calibrate/chunks.py
    ref_band, tgt_band = index_bands([ref_source, tgt_source], [INDEX_COLUMNS, INDEX_COLUMNS],
                                     run.chunk_rows)
    timings["metadata"] = time.perf_counter() - stage
    ratio, r, eps, source = _ratio(opts, pair, label)
    channels = channel_plan(pair, ratio, opts.input.average_channels, label)
    for band, group, role, column in ((ref_source, pair.ref, "reference-band Measurement Set",
                                       columns.ref_data),
                                      (tgt_source, pair.tgt, "target-band Measurement Set",
                                       columns.target_data)):
        check_channel_counts(band.ms, role, column, band.ds, group.n_chan, group.spw)

    stage = time.perf_counter()
    match = GroupMatch(ref_band, tgt_band, ref_stations, tgt_stations, list(pair.ref.corr),
                       list(pair.tgt.corr), antenna_map, opts.input.time_tolerance,
                       datasets={"ref": ref_source.ds, "tgt": tgt_source.ds})
    log.info("stations paired by code (%s: ANTENNA::%s, %s: ANTENNA::%s): %s", run.ref_ms,
             ref_stations.column, run.target_ms, tgt_stations.column,
             ", ".join(f"{e['reference'] or '-'}->{e['target'] or '-'}" for e in match.pairing))
    bounds = chunk_bounds(match.time_counts(), run.chunk_rows)
    if len(bounds) > 2:
        # one dataset per band whose row blocks are the chunks, read by both passes; the
        # robust trackers read reference context beyond each chunk: finer blocks there
        match = match.with_datasets(match.chunk_datasets(
            bounds, {"tgt": ROW_COLUMNS + ["ROWID"] + columns.tgt,
                     "ref": ROW_COLUMNS + ["ROWID"] + columns.ref + columns.snr},
            split={"ref": 1 if opts.tracking.tracker == "count" else 8}))
    # every chunk's cells are checked (duplicates, matches, scans) before anything is written
    checked = match.check(bounds)
    grid = TrackGrid(times=match.times, ant1=match.ant1, ant2=match.ant2,
                     baseline_names=match.baseline_names,
                     scans=_split_long_gaps(checked.scans, match.times,
                                            float(opts.tracking.coherence_time)))
    timings["match"] = time.perf_counter() - stage
    from .tracking_setup import tracking_setup
    setup = tracking_setup(opts, grid, run.target_ms, tgt_stations.codes, columns.snr_from,
                           run.tgt_meta)
    _log_match(run, match, grid, checked, tgt_band.n_row)
    return GroupPlan(pair=pair, label=label, match=match, grid=grid, bounds=bounds,
                     first_chunk=checked.first_chunk, ratio=ratio, r=r, eps=eps,
                     ratio_source=source, tracking=setup, n_target_rows=tgt_band.n_row,
                     n_matched=checked.n_matched, n_ref_unused=checked.n_ref_unused,
                     antenna_names=list(tgt_stations.codes), channels=channels)


def _split_long_gaps(scans: ScanAxis, times: np.ndarray, coherence_time: float) -> ScanAxis:
    """The tracking scans: no wrap is counted across a stretch without data, whatever
    SCAN_NUMBER says."""
    steps = np.diff(times)
    min_gap = max(5.0 * float(np.median(steps)) if steps.size else 0.0, coherence_time)
    scans, splits = scans.split_at_gaps(times, min_gap)
    if splits:
        log.info("%d time gap(s) longer than %.0f s inside scans start new tracking scans "
                 "(SCAN_NUMBER %s)", len(splits), min_gap,
                 ", ".join(f"{s.scan_number} at +{s.time - times[0]:.0f} s after {s.gap_s:.0f} s"
                           for s in splits[:6]) + (" ..." if len(splits) > 6 else ""))
    return scans


def _log_match(run: RunPlan, match: GroupMatch, grid: TrackGrid, checked: MatchCheck,
               n_target_rows: int) -> None:
    for c, name in enumerate(match.corr_names):
        if match.corr_map[0, c] < 0:
            log.warning("correlation %s of %s has no counterpart in %s: flagged in the output",
                        name, run.target_ms, run.ref_ms)
    log.info("matched %d of %d target rows to %s (time tolerance %.3g s, %d baselines, "
             "%d times, %d scans); %d reference rows unused",
             checked.n_matched, n_target_rows, run.ref_ms, match.tolerance, match.n_bl,
             match.n_time, grid.scans.n_scan, checked.n_ref_unused)
    if checked.n_matched < n_target_rows:
        log.warning("%d target rows have no reference row (time/station) and are flagged",
                    n_target_rows - checked.n_matched)
