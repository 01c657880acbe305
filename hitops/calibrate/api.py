"""``hitops calibrate``: frequency phase transfer between two Measurement Sets.

Stages (each in its own module):
1. check the inputs (paths, columns, spectral windows, fields, channels, R)
   before anything is written, so bad input leaves both sets untouched;
2. read the per-row metadata with dask-ms in blocks of at most ``chunk_rows``
   rows, keeping per-time and per-baseline summaries only, and check every
   time chunk's match before anything is written
   (:mod:`hitops.calibrate.chunks`: memory bounded by ``chunk_rows``);
3. cut the union time axis into chunks of at most ``chunk_rows`` target
   rows; for each chunk read the data columns, run
   :func:`hitops.calibrate.transfer.transfer_group` on baseline groups as
   dask tasks (wrap counts carried across chunks) and write the output
   columns and flags through dask-ms;
4. with an offset-reference column, a first pass only accumulates the
   circular-mean offsets, the n0 candidates are chosen per baseline,
   correlation and scan (:mod:`hitops.calibrate.offsets`), and the second
   pass writes;
5. write the JSON report and log the summary.

Output flags: FLAG is backed up once into FLAG_HITOPS_BACKUP (the first time
hitops writes to the set), then FLAG becomes FLAG | FLAG_ROW | (samples that
could not be calibrated).  See docs/calibrate.md.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from ..errors import HitopsError, InputError, MeasurementSetError, OutputExistsError
from ..io import access
from ..io import read as msio
from ..io.match import parse_antenna_map
from ..io.stations import read_stations
from ..options import make_options
from .chunks import INDEX_COLUMNS, ROW_COLUMNS, BandIndex, ChunkMatch, index_bands
from .groups import describe_groups, pair_groups
from .output import (FLAG_BACKUP, STAGING_PREFIX, OutputTransaction, drop_stale_columns,
                     release_cluster_tables)

log = logging.getLogger("hitops.calibrate")

DEFAULT_COLUMNS = {"pwc": "PWC_DATA", "cfpt": "CFPT_DATA", "cwu": "CWU_DATA"}
#: output columns are written under STAGING_PREFIX and renamed when complete, so a run that
#: is killed leaves nothing that looks like a result (hitops/calibrate/output.py)
META_COLUMNS = INDEX_COLUMNS


def parse_methods(method) -> List[str]:
    items = method if isinstance(method, (list, tuple)) else str(method or "").split(",")
    methods = [m.strip().lower() for m in items if m and m.strip()]
    if not methods:
        raise InputError("--method is empty; give one or more of pwc, cfpt, cwu (e.g. --method pwc,cfpt)")
    for m in methods:
        if m not in DEFAULT_COLUMNS:
            raise InputError(f"--method: unknown method '{m}'; choose from pwc, cfpt, cwu")
    if len(set(methods)) != len(methods):
        raise InputError(f"--method lists a method twice: {','.join(methods)}")
    return methods


def split_ratio(ratio: float):
    """(r, eps) with R = r + eps; R within 1e-9 of an integer counts as that integer."""
    nearest = round(ratio)
    if abs(ratio - nearest) < 1e-9:
        return int(nearest), 0.0
    r = math.floor(ratio)
    return int(r), float(ratio - r)


def _average(data: np.ndarray, flag: np.ndarray, flag_row: np.ndarray):
    """(n_row, n_corr) visibility and validity from (n_row, n_chan, n_corr) data.

    One channel: the channel itself.  Several: the mean of unflagged finite
    channels.  Non-finite and zero values are rejected later by the kernels.
    """
    good = ~flag & ~flag_row[:, None, None]
    if data.shape[1] == 1:
        return data[:, 0, :], good[:, 0, :]
    good = good & np.isfinite(data)
    n_good = good.sum(axis=1)
    total = np.where(good, data, 0).sum(axis=1)
    vis = (total / np.maximum(n_good, 1)).astype(np.complex64)
    return vis, n_good > 0


def _rows_from_budget(budget: int, ref_ms: str, target_ms: str, ref_column: str,
                      target_column: str, n_methods: int) -> int:
    """Rows per time chunk that keep the run within ``budget`` bytes (hitops/calibrate/memory.py)."""
    from casacore import tables as pt

    from .memory import rows_for_budget
    n_rows, n_corr, n_chan = 0, 1, 1
    for ms, column in ((ref_ms, ref_column), (target_ms, target_column)):
        with pt.table(ms, ack=False) as t:
            n_rows += t.nrows()
            if t.nrows():
                shape = t.getcell(column, 0).shape
                n_chan, n_corr = max(n_chan, int(shape[0])), max(n_corr, int(shape[-1]))
    rows = rows_for_budget(budget, n_rows, n_corr, n_chan, n_methods)
    log.info("memory budget %.0f MB: up to %d target rows per time chunk (--chunk-rows "
             "overrides)", budget / 1e6, rows)
    return rows


def _chunk_bounds(per_time: np.ndarray, chunk_rows: int):
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


def calibrate(ref_ms, target_ms, method="pwc", ref_column="DATA", target_column="DATA",
              ref_model_column=None, offset_reference_column=None, offset_model=None,
              max_offset_wraps=50, offset_ambiguity_deg=2.0, ratio=None, antenna_map=None, output_column=None,
              overwrite=False, average_channels=False, time_tolerance=None, tracker="count",
              workdir=None, export_uvfits=None,
              half_window=0, coherence_time=20.0, snr=0.0, max_gap=-1, jump_threshold=-1.0,
              jump_window=0, jump_action="segment", refant=None, solve_half_window=-1,
              no_elevation_scaling=False, memory_budget="auto", chunk_rows=0, report=None, scheduler=None,
              lock_timeout=60.0, no_verdict=False, verdict_interval=60.0, caltable=None) -> Dict:
    """Frequency phase transfer from ``ref_ms`` (reference band) to ``target_ms``.

    Writes one column per method into ``target_ms`` (PWC_DATA, CFPT_DATA,
    CWU_DATA by default) holding V_target * exp(-i*(R*phi_cal - 2*pi*eps*n))
    (PWC; CFPT and CWU analogues), updates FLAG (backed up once into
    FLAG_HITOPS_BACKUP) and writes a JSON report (default
    ``<target_ms>.hitops-calibrate.json``).  Returns the report as a dict.

    ``tracker`` picks the reference wrap tracker: ``count`` (the paper's
    step > pi rule), ``smooth`` or ``antenna`` (:mod:`hitops.calibrate.robust`,
    docs/tracking.md); the options after it tune the robust trackers.
    """
    started = time.perf_counter()
    # ---- 1. inputs, all checked before anything is written
    methods = parse_methods(method)
    # ---- issue 13 (hitops/io/convert.py): --export-uvfits checked, UVFITS / FITS-IDI inputs
    # converted once into Measurement Sets in --workdir, before anything is written
    from ..io.convert import prepare_inputs
    ref_ms, target_ms = prepare_inputs(ref_ms, target_ms, workdir, export_uvfits, overwrite,
                                       caltable=caltable, tracker=tracker)
    # ---- end issue 13
    ref_ms = msio.check_ms(ref_ms, "reference-band Measurement Set")
    target_ms = msio.check_ms(target_ms, "target-band Measurement Set")
    if os.path.realpath(ref_ms) == os.path.realpath(target_ms):
        raise InputError(f"REF_MS and TARGET_MS are the same set ({ref_ms}); give the "
                         "reference-band and the target-band Measurement Sets")
    if not float(lock_timeout) >= 0:
        raise InputError(f"--lock-timeout {lock_timeout} must be >= 0 seconds")
    if not float(verdict_interval) > 0:
        raise InputError(f"--verdict-interval {verdict_interval} must be a positive number of "
                         "seconds (e.g. 60)")
    access.require_subtables(ref_ms, "reference-band Measurement Set")
    access.require_subtables(target_ms, "target-band Measurement Set")
    access.require_writable(target_ms, "target-band Measurement Set")
    # one hitops run per target set at a time; then casacore's own locks, whose wait
    # would otherwise be silent and unbounded (hitops/io/access.py)
    with access.RunLock(target_ms, lock_timeout, "target-band Measurement Set"):
        access.wait_for_table_lock(target_ms, True, lock_timeout, "target-band Measurement Set")
        access.wait_for_table_lock(ref_ms, False, lock_timeout, "reference-band Measurement Set")
        drop_stale_columns(target_ms)
        opts = make_options("calibrate", locals())
        try:
            return _calibrate_locked(opts, methods, ref_ms, target_ms, started)
        except RuntimeError as err:
            # casacore's messages do not always say which table failed: find the damage
            access.raise_if_damaged(err, [(ref_ms, [ref_column, "FLAG"] + INDEX_COLUMNS),
                                    (target_ms, [target_column, "FLAG"] + INDEX_COLUMNS)])
            raise
        finally:
            # dask-ms keeps its table handles until they are collected; close them now, so
            # that CASA (its own casacore) or another process can change the set next
            # without this process holding a stale column list
            gc.collect()


def _calibrate_locked(opts, methods: List[str], ref_ms: str, target_ms: str,
                      started: float) -> Dict:
    """The rest of :func:`calibrate`, holding the target set's run lock.

    ``opts``: the validated-so-far options (:func:`hitops.options.options_class`);
    ``ref_ms`` / ``target_ms`` are the checked paths.
    """
    ratio, max_offset_wraps, chunk_rows, tracker = (opts.ratio, opts.max_offset_wraps,
                                                    opts.chunk_rows, opts.tracker)
    half_window, coherence_time, snr, max_gap = (opts.half_window, opts.coherence_time,
                                                 opts.snr, opts.max_gap)
    jump_threshold, jump_window, jump_action = opts.jump_threshold, opts.jump_window, opts.jump_action
    solve_half_window, refant, no_elevation_scaling = (opts.solve_half_window, opts.refant,
                                                       opts.no_elevation_scaling)
    output_column, antenna_map, time_tolerance = (opts.output_column, opts.antenna_map,
                                                  opts.time_tolerance)
    ref_column, ref_model_column, target_column = (opts.ref_column, opts.ref_model_column,
                                                   opts.target_column)
    offset_reference_column, offset_ambiguity_deg = (opts.offset_reference_column,
                                                     opts.offset_ambiguity_deg)
    overwrite, average_channels, scheduler, report = (opts.overwrite, opts.average_channels,
                                                      opts.scheduler, opts.report)
    if ratio is not None and not (float(ratio) > 0 and math.isfinite(float(ratio))):
        raise InputError(f"--ratio {ratio}: R = nu_target / nu_reference must be a positive "
                         "number (e.g. 2.6744 for 230/86 GHz); omit it to take R from the sets")
    if int(max_offset_wraps) < 0:
        raise InputError(f"--max-offset-wraps {max_offset_wraps} must be >= 0")
    if int(chunk_rows) < 0:
        raise InputError(f"--chunk-rows {chunk_rows} must be >= 1 (or 0: from --memory-budget)")
    from .memory import parse_budget
    budget = parse_budget(opts.memory_budget)
    from .robust import check_options
    check_options(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                  jump_window, jump_action, solve_half_window)
    if output_column and len(methods) > 1:
        raise InputError(f"--output-column {output_column} names one column but --method "
                         f"lists {len(methods)} methods; run one method at a time to rename")
    outputs = {m: (output_column or DEFAULT_COLUMNS[m]) for m in methods}
    antenna_map = parse_antenna_map(antenna_map)

    if time_tolerance is not None and not float(time_tolerance) > 0:
        raise InputError(f"--time-tolerance {time_tolerance} must be a positive number of "
                         "seconds; omit it to use half the smallest INTERVAL")
    present = set(msio.column_names(target_ms))
    # a rerun with --overwrite starts from the flags hitops found before its first run
    # (FLAG_HITOPS_BACKUP), so two identical runs give identical FLAG columns; a run that
    # was killed half-way through writing FLAG is repaired the same way
    flag_column = FLAG_BACKUP if (overwrite and FLAG_BACKUP in present) else "FLAG"
    if flag_column == FLAG_BACKUP:
        log.info("--overwrite: starting from %s (the flags before hitops first ran), not "
                 "from FLAG, so this run's flags replace the earlier run's", FLAG_BACKUP)
    ref_cols = [ref_column, "FLAG"] + ([ref_model_column] if ref_model_column else [])
    # --offset-model: 'point' or a model column of TARGET_MS (hitops/calibrate/offsets.py)
    offset_model = opts.offset_model or None
    if offset_model and offset_reference_column:
        raise InputError(f"--offset-model {offset_model} and --offset-reference-column "
                         f"{offset_reference_column} both set the n0 offset step; give one")
    from .offsets import is_point_model
    model_column = offset_model if offset_model and not is_point_model(offset_model) else None
    tgt_cols = [target_column, flag_column] + ([offset_reference_column] if offset_reference_column else []) \
        + ([model_column] if model_column else [])
    msio.require_columns(ref_ms, ref_cols + META_COLUMNS, "reference-band Measurement Set",
                         "check --ref-column / --ref-model-column")
    msio.require_columns(target_ms, tgt_cols + META_COLUMNS, "target-band Measurement Set",
                         "check --target-column / --offset-reference-column / --offset-model")
    protected = {target_column, "FLAG", FLAG_BACKUP, "DATA", offset_reference_column,
                 model_column} - {None}
    for m, col in outputs.items():
        if col.startswith(STAGING_PREFIX):
            raise InputError(f"output column {col}: names starting with {STAGING_PREFIX} are "
                             "hitops's own unfinished columns; choose another --output-column")
        if col in protected:
            raise InputError(f"output column {col} of {target_ms} is an input or flag column; "
                             "choose another --output-column (e.g. PWC_DATA)")
        if col in present and not overwrite:
            raise OutputExistsError(f"column {col} already exists in {target_ms}; pass "
                                    "--overwrite to replace it or --output-column to write "
                                    "another column")

    # the robust trackers take the per-sample SNR from SIGMA or WEIGHT where they are
    # informative (hitops/calibrate/robust.py): that column is read with the data
    snr_from = "data"
    if tracker != "count" and not (float(opts.snr) > 0 or int(opts.half_window) > 0):
        from .robust import sigma_source
        snr_from = sigma_source(ref_ms)
    snr_cols = [snr_from.upper()] if snr_from in ("sigma", "weight") else []
    # a field/spectral-window group is a dask-ms dataset of its own, so FIELD_ID and
    # DATA_DESC_ID are not read per row (hitops/calibrate/groups.py)
    ref_meta_cols = tgt_meta_cols = INDEX_COLUMNS
    timings = {"checks": time.perf_counter() - started}
    stage = time.perf_counter()
    if int(chunk_rows) == 0:
        chunk_rows = _rows_from_budget(budget, ref_ms, target_ms, ref_column, target_column,
                                       len(methods))
    # dask row chunks of chunk_rows rows: the metadata blocks of the first pass are
    # slices of these datasets (no dataset per block)
    io_rows = min(int(chunk_rows), 1 << 21)
    ref_groups = msio.open_groups(ref_ms, list(dict.fromkeys(ref_meta_cols + ref_cols + snr_cols)),
                                  io_rows,
                                  grouped=bool(msio.selection_columns(ref_ms)))
    tgt_groups = msio.open_groups(target_ms, list(dict.fromkeys(tgt_meta_cols + tgt_cols)),
                                  io_rows, grouped=bool(msio.selection_columns(target_ms)))
    timings["open"] = time.perf_counter() - stage
    ref_stations = read_stations(ref_ms, "reference-band Measurement Set")
    tgt_stations = read_stations(target_ms, "target-band Measurement Set")
    ref_names, tgt_names = ref_stations.codes, tgt_stations.codes
    ref_described = describe_groups(ref_ms, ref_groups, "reference-band Measurement Set",
                                    average_channels)
    tgt_described = describe_groups(target_ms, tgt_groups, "target-band Measurement Set",
                                    average_channels)
    pairs = pair_groups(ref_ms, target_ms, ref_described, tgt_described)
    if len(pairs) > 1:
        log.info("%d (field, spectral window) groups calibrated one by one: %s", len(pairs),
                 "; ".join(p.label for p in pairs))
        if opts.caltable:
            raise InputError(f"--caltable {opts.caltable}: the sets hold {len(pairs)} field/"
                             "spectral-window groups and the table holds one; split them "
                             "(CASA split field=/spw=) and write one table per group")
    common = dict(locals())
    plans = [_plan_group(dict(common), pair) for pair in pairs]

    # ---- 2. chunks and the dask machinery
    client = closer = None
    if scheduler:
        # an address, or slurm[:N] (dask-jobqueue worker jobs): hitops/cluster.py
        from ..cluster import dask_client
        client, closer = dask_client(scheduler)
    try:
        return _run_groups(plans, client, started)
    finally:
        if closer is not None:
            closer.close()


def _run_groups(plans: List[Dict], client, started: float) -> Dict:
    """Run every group pair into one OutputTransaction; commit once; the report."""
    first = plans[0]
    # everything this run changes in the target set (hitops/calibrate/output.py)
    tx = OutputTransaction(first["target_ms"], first["outputs"], first["target_column"],
                           None, first["chunk_rows"])
    tx.check_space()
    if client is not None:
        release_cluster_tables(client)   # stale handles of an earlier run on this cluster
        tx.create_columns()
    try:
        results = [_run(g, tx, client) for g in plans]
        if client is not None:
            release_cluster_tables(client)
        tx.commit()
    except BaseException:
        tx.rollback()
        raise
    reports = [_finish(g, *result, tx, started) for g, result in zip(plans, results)]
    if len(reports) == 1:
        return _write_report(first, reports[0], results[0], started)
    return _write_report(first, _combined_report(plans, reports), None, started)


def _plan_group(g: Dict, pair) -> Dict:
    """Index, match and check one (field, spectral window) group pair before anything is
    written; returns the group's run inputs (``g``: the run's checked options and sets)."""
    ref_ms, target_ms, ref_groups, tgt_groups = g["ref_ms"], g["target_ms"], g["ref_groups"], g["tgt_groups"]
    ref_stations, tgt_stations = g["ref_stations"], g["tgt_stations"]
    ref_names, tgt_names = g["ref_names"], g["tgt_names"]
    ref_meta_cols, tgt_meta_cols = g["ref_meta_cols"], g["tgt_meta_cols"]
    ref_cols, tgt_cols, snr_cols = g["ref_cols"], g["tgt_cols"], g["snr_cols"]
    chunk_rows, ratio, tracker, timings = g["chunk_rows"], g["ratio"], g["tracker"], g["timings"]
    antenna_map, time_tolerance = g["antenna_map"], g["time_tolerance"]
    coherence_time = g["coherence_time"]
    grouped = len(g["pairs"]) > 1
    for name in ("pairs", "common", "ref_described", "tgt_described"):
        g.pop(name, None)
    ref_key, tgt_key = pair.ref.key, pair.tgt.key
    ref_index = BandIndex(ms=ref_ms, ds=ref_groups[ref_key], n_ant=len(ref_names),
                          n_row=int(ref_groups[ref_key].sizes["row"]), key=ref_key,
                          grouped=len(ref_groups) > 1)
    tgt_index = BandIndex(ms=target_ms, ds=tgt_groups[tgt_key], n_ant=len(tgt_names),
                          n_row=int(tgt_groups[tgt_key].sizes["row"]), key=tgt_key,
                          grouped=len(tgt_groups) > 1)
    if ref_index.n_row == 0 or tgt_index.n_row == 0:
        empty = ref_ms if ref_index.n_row == 0 else target_ms
        raise MeasurementSetError(f"{empty} has no rows ({pair.label}); nothing to calibrate")
    stage = time.perf_counter()
    # per-row metadata in blocks of at most chunk_rows rows; only summaries stay (and TIME
    # for tables not in time order), see hitops/calibrate/chunks.py
    index_bands([ref_index, tgt_index], [ref_meta_cols, tgt_meta_cols], int(chunk_rows))
    timings["metadata"] = time.perf_counter() - stage
    ref_freq, ref_corr = pair.ref.freq, list(pair.ref.corr)
    tgt_freq, tgt_corr = pair.tgt.freq, list(pair.tgt.corr)
    if ratio is None:
        if not (ref_freq > 0 and tgt_freq > 0):
            raise MeasurementSetError(f"cannot take R from the spectral windows ({ref_freq} Hz, "
                                      f"{tgt_freq} Hz); pass --ratio")
        ratio = tgt_freq / ref_freq
        source = f"from the spectral windows: {tgt_freq / 1e9:.6g} GHz / {ref_freq / 1e9:.6g} GHz"
    else:
        ratio = float(ratio)
        source = "from --ratio"
    r, eps = split_ratio(ratio)
    log.info("%sR = %.10g (%s): r = %d, eps = %.10g; a reference wrap moves CFPT by %.2f deg",
             f"{pair.label}: " if grouped else "", ratio, source, r, eps,
             math.degrees(math.remainder(2 * math.pi * eps, 2 * math.pi)))
    if ratio < 1:
        log.warning("R = %.6g < 1: the target band is below the reference band; FPT scales "
                    "the reference phases down (PWC still applies, eps = R)", ratio)

    stage = time.perf_counter()
    match = ChunkMatch(ref_index, tgt_index, ref_stations, tgt_stations, ref_corr, tgt_corr,
                       antenna_map, time_tolerance)
    log.info("stations paired by code (%s: ANTENNA::%s, %s: ANTENNA::%s): %s", ref_ms,
             ref_stations.column, target_ms, tgt_stations.column,
             ", ".join(f"{e['reference'] or '-'}->{e['target'] or '-'}" for e in match.pairing))
    bounds = _chunk_bounds(match.time_counts(), int(chunk_rows))
    if len(bounds) > 2:
        # one dataset per band whose row blocks are the chunks, read by both passes; the
        # robust trackers read reference context beyond each chunk: finer blocks there
        match.use_chunk_datasets(bounds, {"tgt": ROW_COLUMNS + ["ROWID"] + tgt_cols,
                                          "ref": ROW_COLUMNS + ["ROWID"] + ref_cols + snr_cols},
                                 split={"ref": 1 if tracker == "count" else 8})
    # every chunk's cells are checked (duplicates, matches, scans) before anything is written
    first_chunk = match.check(bounds)
    # no wrap is counted across a stretch without data, whatever SCAN_NUMBER says
    steps = np.diff(match.times)
    min_gap = max(5.0 * float(np.median(steps)) if steps.size else 0.0, float(coherence_time))
    splits = match.split_at_gaps(min_gap)
    if splits:
        log.info("%d time gap(s) longer than %.0f s inside scans start new tracking scans "
                 "(SCAN_NUMBER %s)", len(splits), min_gap,
                 ", ".join(f"{n} at +{t - match.times[0]:.0f} s after {g:.0f} s"
                           for n, t, g in splits[:6]) + (" ..." if len(splits) > 6 else ""))
    timings["match"] = time.perf_counter() - stage
    n_target_rows = tgt_index.n_row
    tracking_setup = _tracking_setup({**g, **locals()})
    n_corr = len(tgt_corr)
    for c, name in enumerate(match.corr_names):
        if match.corr_map[0, c] < 0:
            log.warning("correlation %s of %s has no counterpart in %s: flagged in the output",
                        name, target_ms, ref_ms)
    log.info("matched %d of %d target rows to %s (time tolerance %.3g s, %d baselines, "
             "%d times, %d scans); %d reference rows unused",
             match.n_matched, n_target_rows, ref_ms, match.tolerance, match.n_bl,
             match.n_time, match.scans.size, match.n_ref_unused)
    if match.n_matched < n_target_rows:
        log.warning("%d target rows have no reference row (time/station) and are flagged",
                    n_target_rows - match.n_matched)

    g.update({k: v for k, v in locals().items() if k not in ("g", "pair")})
    g["group"] = pair
    return g


def _tracking_setup(g: Dict):
    """Resolved robust-tracking parameters (None for --tracker count); checks --refant."""
    from .robust import ANTENNA_TRACK_HALF_WINDOW as ROBUST_ANTENNA_H
    from .robust import grid_positions, setup_tracking, station_sin_elevation

    defaults = {"half_window": 0, "coherence_time": 20.0, "snr": 0.0, "max_gap": -1,
                "jump_threshold": -1.0, "jump_window": 0, "jump_action": "segment",
                "refant": None, "solve_half_window": -1, "no_elevation_scaling": False}
    if g["tracker"] == "count":
        changed = [k for k, v in defaults.items() if g[k] != v and not (v is None and not g[k])]
        if changed:
            log.warning("--tracker count ignores %s (they tune --tracker smooth/antenna)",
                        ", ".join("--" + k.replace("_", "-") for k in changed))
        return None
    if g["refant"] and g["tracker"] != "antenna":
        log.warning("--refant is used by --tracker antenna only; ignored")
    _, dt = grid_positions(g["match"].times, g["match"].scan_of_time)
    fixed = float(g["snr"]) > 0 or int(g["half_window"]) > 0
    snr_from = "fixed" if fixed else g["snr_from"]
    sin_el = None
    if not g["no_elevation_scaling"]:
        sin_el = station_sin_elevation(g["target_ms"], g["match"].times)
        if sin_el is None:
            log.info("no station geometry in %s (ANTENNA positions off the Earth's surface): "
                     "--coherence-time is used without elevation scaling", g["target_ms"])
    setup = setup_tracking(g["tracker"], g["half_window"], g["coherence_time"], g["snr"],
                           g["max_gap"], g["jump_threshold"], g["jump_window"], g["jump_action"],
                           g["refant"], g["solve_half_window"], dt, g["tgt_names"], snr_from,
                           elevation_scaling=sin_el is not None)
    setup.sin_elevation = sin_el
    log.info("tracker %s: dt %.4g s, t_c %.4g s%s, half-window %s (SNR %s), max gap %d, jumps %s "
             "(action %s)%s; context %d samples per chunk side", setup.tracker, setup.dt,
             setup.coherence_time,
             " (zenith, x sin(el)^(3/5) per station)" if setup.elevation_scaling else "",
             (f"{ROBUST_ANTENNA_H} on antenna tracks" if setup.tracker == "antenna" else
              setup.half_window if setup.half_window > 0 else f"per sample <= {setup.max_half_window}"),
             f"{setup.snr:.3g}" if setup.snr > 0 else f"from {setup.snr_source}", setup.max_gap,
             f"window {setup.jump_window}, threshold {math.degrees(setup.jump_threshold):.1f} deg"
             if setup.jump_threshold > 0 else "off", setup.jump_action,
             (f"; solve half-window {setup.solve_half_window if setup.solve_half_window >= 0 else 'per time'}"
              if setup.tracker == "antenna" else ""),
             setup.context)
    return setup


def _run(ctx: Dict, tx: OutputTransaction, client) -> tuple:
    """Stages 2-4 of :func:`calibrate` for one group pair, written through ``tx``;
    ``ctx`` holds its validated inputs and metadata.  Returns what the report needs."""
    import dask

    from ..kernels import fpt
    from .chunks import ChunkRows
    from ..tracking.count import Carry
    from .transfer import group_inputs, plan_groups, transfer_group

    g = ctx
    match, methods = g["match"], g["methods"]
    ratio, eps = g["ratio"], g["eps"]
    n_corr = len(g["tgt_corr"])
    n_scan = match.scans.size
    import dask.threaded

    compute_kw = {"scheduler": client.get if client is not None else dask.threaded.get}
    io_scheduler = compute_kw["scheduler"]
    codes = [fpt.METHOD_CODES[m] for m in methods]
    bounds = g["bounds"]
    n_chunks = len(bounds) - 1
    n_workers = (len(client.scheduler_info()["workers"]) if client is not None
                 else (os.cpu_count() or 1))
    groups = plan_groups(match.n_bl, 2 * n_workers)
    log.info("%d chunk(s) of <= %d target rows; %d baseline groups; scheduler %s",
             n_chunks, int(g["chunk_rows"]), len(groups), g["scheduler"] or "threads")

    ref_cols, tgt_cols = g["ref_cols"], g["tgt_cols"]
    setup = g["tracking_setup"]
    from .robust import ReferenceTracker, apply_segment_offsets, gather_grid
    ref_read_cols = list(ref_cols)
    if setup is not None and setup.snr_source in ("sigma", "weight"):
        ref_read_cols.append(setup.snr_source.upper())

    def new_tracker():
        if setup is None:
            return None
        return ReferenceTracker(setup, match, match.corr_names, len(g["tgt_names"]),
                                list(g["tgt_names"]), workers=1 if client is not None else 0,
                                sin_elevation=getattr(setup, "sin_elevation", None))

    tracker = new_tracker()   # for the chunk extents; each pass tracks afresh
    # what the n0 offset step compares the output with: a reference calibration's column,
    # a model column, or 'point' (no column: phase 0)
    off_col = g["offset_reference_column"] or g["offset_model"]
    cache = {}

    two_pass = bool(off_col) and g["eps"] != 0.0 and (fpt.PWC in codes or fpt.CWU in codes)
    timings = g["timings"]
    for key in ("read", "transfer", "write"):
        timings[key] = 0.0

    def load(i):
        if i in cache:
            return cache[i]
        stage = time.perf_counter()
        t0, t1 = bounds[i], bounds[i + 1]
        # robust trackers read `context` extra reference times on either side
        t_lo, t_hi = tracker.extended(t0, t1) if tracker is not None else (t0, t1)
        # the chunk's rows and their grid cells; the metadata is read with the data (or
        # reused from the checks when the whole track is one chunk)
        first = g["first_chunk"] if (n_chunks == 1 and (t_lo, t_hi) == (t0, t1)) else None
        t_rows = match.row_numbers("tgt", t0, t1)
        r_rows = match.row_numbers("ref", t_lo, t_hi)
        t_read = list(dict.fromkeys(list(tgt_cols) + ([] if first or match.tgt.whole
                                                      else ROW_COLUMNS + ["ROWID"])))
        r_read = list(dict.fromkeys(list(ref_read_cols) + ([] if first or match.ref.whole
                                                            else ROW_COLUMNS + ["ROWID"])))
        tgt, ref = msio.compute_columns([match.chunk_request("tgt", t_rows, t_read),
                                         match.chunk_request("ref", r_rows, r_read)],
                                        scheduler=io_scheduler)
        if first:
            t_idx, r_idx = first
        else:
            t_idx = match.index_rows("tgt", tgt if not match.tgt.whole else
                                     match.read_meta("tgt", t_rows, ROW_COLUMNS + ["ROWID"]))
            r_idx = match.index_rows("ref", ref if not match.ref.whole else
                                     match.read_meta("ref", r_rows, ROW_COLUMNS + ["ROWID"]))
        # reference rows whose station pair has no target baseline take no part
        keep = r_idx.bl >= 0
        if not keep.all():
            ref = {c: v[keep] for c, v in ref.items()}
            r_idx = ChunkRows(rows=r_idx.rows[keep], bl=r_idx.bl[keep], time=r_idx.time[keep],
                              swapped=r_idx.swapped[keep], flag_row=r_idx.flag_row[keep],
                              scan=None)
        tgt_rows, ref_rows = t_idx.rows, r_idx.rows
        tgt_flag_row, ref_flag_row = t_idx.flag_row, r_idx.flag_row
        if g["flag_column"] != "FLAG":   # --overwrite: the flags before hitops's first run
            tgt["FLAG"] = tgt.pop(g["flag_column"])
        tvis, tok = _average(tgt[g["target_column"]], tgt["FLAG"], tgt_flag_row)
        rvis, rok = _average(ref[g["ref_column"]], ref["FLAG"], ref_flag_row)
        if g["ref_model_column"]:
            mvis, _ = _average(ref[g["ref_model_column"]], np.zeros_like(ref["FLAG"]),
                               np.zeros_like(ref_flag_row))
            rvis = rvis * np.conj(mvis)
        ext = None
        if tracker is not None:
            sigma = None
            if setup.snr_source == "sigma":
                sigma = np.asarray(ref["SIGMA"], dtype=np.float64)
            elif setup.snr_source == "weight":
                with np.errstate(divide="ignore"):
                    sigma = 1.0 / np.sqrt(np.asarray(ref["WEIGHT"], dtype=np.float64))
            ext_grid = np.full((match.n_bl, t_hi - t_lo), -1, dtype=np.int64)
            ext_grid[r_idx.bl, r_idx.time - t_lo] = np.arange(ref_rows.size)
            ext = (t_lo, t_hi) + gather_grid(ext_grid, rvis, rok, r_idx.swapped,
                                             match.corr_map, sigma)
            del ext_grid
            inner = (r_idx.time >= t0) & (r_idx.time < t1)
            ref_rows, rvis, rok = ref_rows[inner], rvis[inner], rok[inner]
            r_idx = ChunkRows(rows=ref_rows, bl=r_idx.bl[inner], time=r_idx.time[inner],
                              swapped=r_idx.swapped[inner], flag_row=None, scan=None)
        ovis = ook = None
        if off_col and off_col == g["offset_model"] and g["model_column"] is None:
            ovis = np.ones(tvis.shape, np.complex64)          # --offset-model point
            ook = np.ones(tvis.shape, bool)
        elif off_col:
            ovis, ook = _average(tgt[off_col], tgt["FLAG"], tgt_flag_row)
        n_t = t1 - t0
        tgt_grid = np.full((match.n_bl, n_t), -1, dtype=np.int64)
        tgt_grid[t_idx.bl, t_idx.time - t0] = np.arange(tgt_rows.size)
        ref_grid = np.full((match.n_bl, n_t), -1, dtype=np.int64)
        ref_grid[r_idx.bl, r_idx.time - t0] = np.arange(ref_rows.size)
        chunk = dict(t0=t0, t1=t1, tgt_rows=tgt_rows, tgt_data=tgt[g["target_column"]],
                     tgt_flag=tgt["FLAG"], tgt_flag_row=tgt_flag_row, tgt_vis=tvis, tgt_ok=tok,
                     ref_vis=rvis, ref_ok=rok, ref_swapped=r_idx.swapped,
                     off_vis=ovis, off_ok=ook, tgt_grid=tgt_grid, ref_grid=ref_grid, ext=ext)
        if n_chunks == 1 and two_pass:   # keep the data for the second pass
            cache[i] = chunk
        timings["read"] += time.perf_counter() - stage
        return chunk

    # one chunk with the offset step and a robust tracker: the first pass keeps its output,
    # and the step shifts it by 2 pi eps k per segment before writing (no second pass; the
    # same as one to complex64 rounding)
    kept = {} if (n_chunks == 1 and two_pass and setup is not None) else None

    def run_pass(offsets, write, segment_k=None):
        nonlocal tracker
        tracker = new_tracker()
        seg_sums = {}
        ref_carry = Carry.empty(match.n_bl, n_corr)
        tgt_carry = Carry.empty(match.n_bl, n_corr)
        totals = {"n_samples": 0, "target_invalid": 0, "no_reference_row": 0,
                  "reference_invalid": 0, "other_uncalibrated": 0}
        wrap_events = np.zeros((match.n_bl, n_corr), dtype=np.int64)
        sums = np.zeros((match.n_bl, n_corr, n_scan), dtype=np.complex128)
        counts = np.zeros((match.n_bl, n_corr, n_scan), dtype=np.int64)
        for i in range(n_chunks):
            ch = load(i)
            stage = time.perf_counter()
            scan_local = match.scan_of_time[ch["t0"]:ch["t1"]]
            ref_wraps = ref_exclude = seg_keys = ref_model = None
            if tracker is not None:
                t_lo, t_hi, ext_vis, ext_valid, ext_sigma = ch["ext"]
                ref_wraps, ref_exclude, seg_keys, ref_model = tracker.track(
                    t_lo, ch["t0"], ch["t1"], t_hi, ext_vis, ext_valid, ext_sigma)
                ref_wraps = apply_segment_offsets(ref_wraps, seg_keys, segment_k)
            tasks = []
            # the first pass of a kept chunk sums the offsets here, from the rows (the groups
            # then need neither the target phases nor the reference/model column)
            in_groups = offsets is None and kept is None
            for bls in groups:
                gi = group_inputs(bls, ch["tgt_grid"], ch["ref_grid"], ch["tgt_vis"],
                                  ch["tgt_ok"], ch["ref_vis"], ch["ref_ok"], ch["ref_swapped"],
                                  ch["off_vis"] if in_groups else None,
                                  ch["off_ok"] if in_groups else None,
                                  local=client is not None)
                picked = gi.pop("tgt_picked")
                local_grid = gi["tgt_rows"]
                if picked is None:   # shared chunk arrays: the grid holds chunk row indices
                    local_grid, picked = None, gi["tgt_rows"]
                gi.update(corr_map=match.corr_map, scan_of_time=scan_local, n_scan=n_scan,
                          methods=codes, ratio=ratio, eps=eps,
                          ref_wraps=None if ref_wraps is None else ref_wraps[bls],
                          ref_model=None if ref_model is None else ref_model[bls],
                          ref_exclude=None if ref_exclude is None else ref_exclude[bls],
                          segment_keys=(seg_keys[bls] if seg_keys is not None and offsets is None
                                        and off_col else None),
                          ref_carry=ref_carry.subset(bls), tgt_carry=tgt_carry.subset(bls),
                          offsets=None if offsets is None else offsets[bls])
                tasks.append((bls, picked, local_grid,
                              dask.delayed(transfer_group, pure=False)(gi)))
            results = dask.compute(*[t[3] for t in tasks], **compute_kw)
            tasks = [t[:3] for t in tasks]   # drop the group inputs as soon as possible
            n_rows = ch["tgt_rows"].size
            if tasks[0][2] is None:
                # threads: the groups are consecutive baselines whose cells hold chunk rows,
                # so their grids stacked are the chunk's grid (one numba pass to row order)
                phasor_rows = {c: fpt.scatter_rows(
                    ch["tgt_grid"], np.concatenate([r["phasors"][c] for r in results]),
                    n_rows, np.complex64(0)) for c in codes}
                calibrated = fpt.scatter_rows(
                    ch["tgt_grid"], np.concatenate([r["calibrated"] for r in results]),
                    n_rows, False)
            else:   # remote workers: each group's cells hold its own compact rows
                phasor_rows = {c: np.zeros((n_rows, n_corr), np.complex64) for c in codes}
                calibrated = np.zeros((n_rows, n_corr), dtype=bool)
                for (bls, picked, local_grid), res in zip(tasks, results):
                    for c in codes:
                        phasor_rows[c][picked] = fpt.scatter_rows(
                            local_grid, res["phasors"][c], picked.size, np.complex64(0))
                    calibrated[picked] = fpt.scatter_rows(local_grid, res["calibrated"],
                                                          picked.size, False)
            for (bls, picked, local_grid), res in zip(tasks, results):
                for key in totals:
                    totals[key] += res[key]
                wrap_events[bls] += res["wrap_events"]
                if "offset_sums" in res:
                    sums[bls] += res["offset_sums"]
                    counts[bls] += res["offset_counts"]
                if "segment_sums" in res:
                    for (lb, c, key), z, n in zip(*res["segment_sums"]):
                        entry = seg_sums.setdefault((int(bls[lb]), int(c), int(key)), [0j, 0])
                        entry[0] += z
                        entry[1] += int(n)
                _merge_carry(ref_carry, bls, res["ref_carry"])
                _merge_carry(tgt_carry, bls, res["tgt_carry"])
            ref_carry.last_scan = int(scan_local[-1])
            tgt_carry.last_scan = int(scan_local[-1])
            if not write and kept is not None:
                kept[i] = (phasor_rows, calibrated, seg_keys)
                if offsets is None and off_col:
                    from .lattice import segment_row_sums
                    method = fpt.PWC if fpt.PWC in codes else fpt.CWU
                    for (b, c, key), z, n in zip(*segment_row_sums(
                            ch["tgt_grid"], seg_keys, ch["tgt_vis"], phasor_rows[method],
                            calibrated, ch["off_vis"], ch["off_ok"])):
                        entry = seg_sums.setdefault((int(b), int(c), int(key)), [0j, 0])
                        entry[0] += z
                        entry[1] += int(n)
            timings["transfer"] += time.perf_counter() - stage
            if write:
                stage = time.perf_counter()
                _write_chunk(tx, ch, phasor_rows, calibrated, codes, io_scheduler)
                timings["write"] += time.perf_counter() - stage
        if tracker is not None:
            wrap_events = tracker.stats.per_series["wrap_events"].copy()
            totals["jump_flagged"] = int(tracker.stats.per_series["jump_flagged"].sum())
        if not write and kept is not None:
            kept["result"] = (totals, wrap_events)
        if tracker is not None and offsets is None and off_col:
            return totals, wrap_events, seg_sums, None
        return totals, wrap_events, sums, counts

    def write_kept(segment_k):
        """The writing pass from the first pass's kept output, shifted by the step's k."""
        from .offsets import offset_shift_rows
        totals, wrap_events = kept.pop("result")
        for i in range(n_chunks):
            ch = load(i)
            phasor_rows, calibrated, seg_keys = kept.pop(i)
            stage = time.perf_counter()
            offset_shift_rows(ch["tgt_grid"], eps, segment_k, seg_keys,
                              [phasor_rows[c] for c in codes if c in (fpt.PWC, fpt.CWU)])
            timings["offset_apply"] = timings.get("offset_apply", 0.0) + time.perf_counter() - stage
            stage = time.perf_counter()
            _write_chunk(tx, ch, phasor_rows, calibrated, codes, io_scheduler)
            timings["write"] += time.perf_counter() - stage
        return totals, wrap_events, None, None

    offsets, offset_report = _offset_pass(g, run_pass, codes, n_corr, n_scan,
                                          first_tracker=lambda: tracker)
    # robust trackers: offsets stays zero, the per-segment k goes into the counts
    if kept:   # one chunk, robust tracker: the first pass's output, shifted
        totals, wrap_events, _, _ = write_kept(g.get("_segment_k"))
    else:
        totals, wrap_events, _, _ = run_pass(offsets, write=True, segment_k=g.get("_segment_k"))
    return totals, wrap_events, offsets, offset_report, tracker, setup, n_chunks


def _offset_pass(g, run_pass, codes, n_corr, n_scan, first_tracker=None):
    """The n0 offset step's first pass; (offsets, report).

    Compared with ``--offset-reference-column`` (a reference calibration) or
    ``--offset-model`` (``point`` or a model column).  Per baseline the lattice
    point nearest the circular mean (:func:`hitops.calibrate.offsets.choose_offset`;
    per scan with ``count``, per segment with the robust trackers); with
    ``--tracker antenna`` (against a model or a reference column) the parallel hands
    get integers per antenna and segment from one lattice solve over every baseline
    and both hands (:func:`hitops.calibrate.offsets.antenna_offsets`), so closure
    phases are kept.  ``first_tracker``: returns the first pass's tracker (its
    antenna phases tie the hands).
    """
    from ..kernels import fpt
    from .offsets import antenna_offsets, choose_offset
    from .robust import SEGMENT_KEY

    match, eps, setup = g["match"], g["eps"], g["tracking_setup"]
    off_col = g["offset_reference_column"] or g["offset_model"]
    option = "--offset-model" if g["offset_model"] else "--offset-reference-column"
    offsets = None
    offset_report = []
    if off_col and fpt.PWC not in codes and fpt.CWU not in codes:
        log.warning("%s applies to pwc and cwu only; ignored for cfpt", option)
    elif off_col:
        if eps == 0.0:
            log.info("integer R: PWC has no n0 offset; the offset step is skipped")
        else:
            _, _, sums, counts = run_pass(None, write=False)
            stage = time.perf_counter()
            offsets = np.zeros((match.n_bl, n_corr, n_scan))
            if setup is not None:
                # robust trackers: the n0 step per segment (every scan starts one; long gaps
                # and jumps start more); k is added to the segment's wrap count
                segment_k = {}
                if setup.tracker == "antenna":
                    # antenna mode (against a model or a reference column): integers per
                    # antenna and segment, solved on the lattice with every baseline and
                    # both parallel hands at once
                    antenna_corrs = {c for c, name in enumerate(match.corr_names)
                                     if len(name) == 2 and name[0] == name[1]}
                    tr = first_tracker() if first_tracker is not None else None
                    hands = None if getattr(tr, "antenna_phase", None) is None else {
                        "phase": tr.antenna_phase, "segment": tr.antenna_segment,
                        "scan_of_time": match.scan_of_time}
                    seg_k, antennas, solves, series = antenna_offsets(
                        sums, antenna_corrs, match.ant1, match.ant2, list(g["tgt_names"]),
                        match.baseline_names, match.corr_names, match.scans, eps,
                        int(g["max_offset_wraps"]), float(g["offset_ambiguity_deg"]),
                        refants=setup.refants, segment_key=int(SEGMENT_KEY), hands=hands)
                    segment_k.update(seg_k)
                    offset_report.extend(series)
                    g["_offset_antennas"], g["_offset_solves"] = antennas, solves
                    _log_antenna_offsets(antennas, solves)
                    sums = {key: v for key, v in sums.items() if key[1] not in antenna_corrs}
                for (b, c, key), (z, n) in sorted(sums.items()):
                    choice = choose_offset(complex(z), int(n), eps, int(g["max_offset_wraps"]),
                                           float(g["offset_ambiguity_deg"]))
                    entry = {"baseline": match.baseline_names[b],
                             "correlation": match.corr_names[c],
                             "scan": int(match.scans[key // SEGMENT_KEY]),
                             "segment": int(key % SEGMENT_KEY)}
                    if choice is None:
                        entry.update(k=0, samples=0, note="no sample to compare; offset 0")
                    else:
                        segment_k[(b, c, key)] = choice.k
                        entry.update(choice.as_dict())
                        if choice.ambiguous:
                            log.warning("offset step %s %s scan %d segment %d ambiguous: k = %d "
                                        "(residual %.2f deg) vs k = %d (%.2f deg)",
                                        entry["baseline"], entry["correlation"], entry["scan"],
                                        entry["segment"], choice.k, choice.residual_deg,
                                        choice.runner_up_k, choice.runner_up_residual_deg)
                    offset_report.append(entry)
                g["_segment_k"] = segment_k
            for b in range(match.n_bl if setup is None else 0):
                for c in range(n_corr):
                    for s in range(n_scan):
                        choice = choose_offset(complex(sums[b, c, s]), int(counts[b, c, s]), eps,
                                               int(g["max_offset_wraps"]),
                                               float(g["offset_ambiguity_deg"]))
                        entry = {"baseline": match.baseline_names[b],
                                 "correlation": match.corr_names[c],
                                 "scan": int(match.scans[s])}
                        if choice is None:
                            entry.update(k=0, samples=0, note="no sample to compare; offset 0")
                        else:
                            offsets[b, c, s] = 2 * math.pi * eps * choice.k
                            entry.update(choice.as_dict())
                            if choice.ambiguous:
                                log.warning(
                                    "offset step %s %s scan %d ambiguous: k = %d (residual "
                                    "%.2f deg) vs k = %d (%.2f deg); bound --max-offset-wraps "
                                    "or use a better offset reference",
                                    entry["baseline"], entry["correlation"], entry["scan"],
                                    choice.k, choice.residual_deg, choice.runner_up_k,
                                    choice.runner_up_residual_deg)
                        offset_report.append(entry)
            chosen = [e for e in offset_report if e.get("samples") and e.get("solve") != "antenna"]
            if chosen or g.get("_offset_solves") is None:
                log.info("offset step: n0 chosen per baseline for %d series (|k| <= %d); %d "
                         "ambiguous; k values: %s", len(chosen), int(g["max_offset_wraps"]),
                         sum(bool(e.get("ambiguous")) for e in chosen),
                         ", ".join(f"{e['baseline']} {e['correlation']} s{e['scan']}"
                                   + (f"/{e['segment']}" if "segment" in e else "")
                                   + f": {e['k']}" for e in chosen[:12])
                         + (" ..." if len(chosen) > 12 else ""))
            g["timings"]["offset_solve"] = time.perf_counter() - stage
    return offsets, offset_report


def _log_antenna_offsets(antennas, solves) -> None:
    """One line per lattice solve (correlation, scan), warnings for ambiguous antennas."""
    for sv in solves:
        members = [e for e in antennas if e["correlation"] == sv["correlation"]
                   and e["scan"] == sv["scan"]]
        log.info("offset step %s scan %d (antenna lattice, %s, reference %s): %s; coherence "
                 "%.4f, baseline mismatch rms %.2f deg, worst %s %.2f deg",
                 sv["correlation"], sv["scan"], sv["method"], sv["reference"],
                 ", ".join(f"{e['antenna']}/{e['segment']} k={e['k']}"
                           + (f" (margin {e['margin_deg']:.1f} deg)"
                              if e.get("margin_deg") is not None else "") for e in members[:16])
                 + (" ..." if len(members) > 16 else ""),
                 sv["coherence"], sv["residual_rms_deg"] or 0.0, sv["worst_baseline"],
                 sv["worst_residual_deg"] or 0.0)
    for e in antennas:
        if e.get("ambiguous"):
            log.warning("offset step %s %s scan %d segment %d ambiguous: k = %d (residual "
                        "%.2f deg) vs k = %d (%.2f deg); margin %.2f deg < "
                        "--offset-ambiguity-deg", e["antenna"], e["correlation"], e["scan"],
                        e["segment"], e["k"], e["residual_deg"], e["runner_up_k"],
                        e["runner_up_residual_deg"], e["margin_deg"])
    log.info("offset step: %d antenna segments solved on the 2 pi eps k lattice in %d solves; "
             "%d ambiguous", len(antennas), len(solves),
             sum(bool(e.get("ambiguous")) for e in antennas))


def _finish(g, totals, wrap_events, offsets, offset_report, tracker, setup, n_chunks, tx,
            started):
    """The log lines and the report of one finished group pair."""
    match, methods, outputs = g["match"], g["methods"], g["outputs"]
    ref_ms, target_ms, eps = g["ref_ms"], g["target_ms"], g["eps"]
    off_col, timings = g["offset_reference_column"], g["timings"]
    elapsed = time.perf_counter() - started
    n_samples = totals["n_samples"]
    flagged = (totals["target_invalid"] + totals["no_reference_row"]
               + totals["reference_invalid"] + totals["other_uncalibrated"])
    log.info("%d of %d target samples (row x correlation) not calibrated, each counted once: "
             "%d flagged/NaN/zero in the target, %d without a reference row, %d with the "
             "reference sample flagged/NaN/zero%s; %d calibrated", flagged, n_samples,
             totals["target_invalid"], totals["no_reference_row"], totals["reference_invalid"],
             (f", {totals['other_uncalibrated']} other" if totals["other_uncalibrated"] else ""),
             n_samples - flagged)
    for b, name in enumerate(match.baseline_names):
        log.info("wraps %s: %s", name, ", ".join(f"{cn} {int(wrap_events[b, c])}"
                                                 for c, cn in enumerate(match.corr_names)))
    tracking_report = None
    if tracker is not None:
        tracking_report = tracker.report(match.times)
        resolved = g.get("_segment_k") is not None
        tracking_report["segment_offsets"] = (
            "offset step per antenna and segment, solved on the lattice against the model "
            "(--offset-model)" if g.get("_offset_solves") is not None else
            f"offset step per segment ({'--offset-model' if g['offset_model'] else '--offset-reference-column'})"
            if resolved else
            "per antenna (antenna mode)" if setup.tracker == "antenna" else "best guess")
        _log_tracking(tracking_report, setup, resolved)
    report = {
        "ref_ms": ref_ms, "target_ms": target_ms, "methods": methods, "columns": outputs,
        "ratio": g["ratio"], "r": g["r"], "eps": eps, "ratio_source": g["source"],
        "time_tolerance_s": match.tolerance, "tracker": g["tracker"], "chunks": n_chunks,
        "stations": match.pairing,
        "tracking": tracking_report if tracking_report is not None else {
            "setup": {"tracker": "count"},
            "baselines": [{"baseline": name, "wrap_events": int(wrap_events[b].sum())}
                          for b, name in enumerate(match.baseline_names)]},
        "flags": {"column": "FLAG", "backup_column": FLAG_BACKUP,
                  "flag_updated": tx.flag_written,
                  "input_flags": g["flag_column"],
                  "backup_created": tx.backup_written},
        "rows": {"target": int(g["n_target_rows"]), "matched": match.n_matched,
                 "reference_unused": match.n_ref_unused},
        "samples": {"target": n_samples, "flagged": flagged,
                    "no_reference_row": totals["no_reference_row"],
                    "target_invalid": totals["target_invalid"],
                    "reference_invalid": totals["reference_invalid"],
                    "other_uncalibrated": totals["other_uncalibrated"],
                    "jump_flagged": totals.get("jump_flagged", 0),
                    "causes": "disjoint: target_invalid + no_reference_row + reference_invalid "
                              "+ other_uncalibrated = flagged"},
        "wraps": [{"baseline": name, "correlation": cn, "wrap_events": int(wrap_events[b, c])}
                  for b, name in enumerate(match.baseline_names)
                  for c, cn in enumerate(match.corr_names)],
        "offset_step": {"column": off_col, "max_offset_wraps": int(g["max_offset_wraps"]),
                        "applied_to": [m for m in methods if m in ("pwc", "cwu")] if offsets is not None else [],
                        "per": "segment" if g.get("_segment_k") is not None else "scan",
                        "model": g["offset_model"],
                        "solve": ("antenna lattice" if g.get("_offset_solves") is not None
                                  else "baseline" if offsets is not None else None),
                        "antennas": g.get("_offset_antennas", []),
                        "solves": g.get("_offset_solves", []),
                        "warning": _no_offset_step(g, offsets, setup),
                        "series": offset_report},
        "time_s": elapsed,
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
    }
    return report


def _combined_report(plans: List[Dict], reports: List[Dict]) -> Dict:
    """One report for several group pairs: the run's entries, then one entry per group."""
    first = reports[0]
    groups = []
    for g, rep in zip(plans, reports):
        pair = g["group"]
        entry = {"field": pair.tgt.field, "ref_field_id": pair.ref.key[0],
                 "target_field_id": pair.tgt.key[0], "ref_spw": pair.ref.spw,
                 "target_spw": pair.tgt.spw, "ref_freq_hz": pair.ref.freq,
                 "target_freq_hz": pair.tgt.freq}
        entry.update({k: v for k, v in rep.items()
                      if k not in ("ref_ms", "target_ms", "methods", "columns", "flags",
                                   "time_s", "timings_s")})
        groups.append(entry)
    return {"ref_ms": first["ref_ms"], "target_ms": first["target_ms"],
            "methods": first["methods"], "columns": first["columns"],
            "ratio": [e["ratio"] for e in groups], "flags": first["flags"],
            "groups": groups, "time_s": first["time_s"],
            "timings_s": {k: round(sum(r["timings_s"].get(k, 0.0) for r in reports), 4)
                          for k in first["timings_s"]}}


def _write_report(g: Dict, report: Dict, result, started: float) -> Dict:
    """The verdict, the calibration table and conversions of a run; the JSON report written."""
    outputs, target_ms, ref_ms = g["outputs"], g["target_ms"], g["ref_ms"]
    n_chunks = result[-1] if result is not None else None
    if g["opts"].no_verdict:
        pass
    elif result is None:
        # the verdict reads both bands whole (hitops/calibrate/verdict.py), every group mixed
        log.info("no verdict: the sets hold several field/spectral-window groups and the "
                 "verdict reads each band whole")
        report["verdict"] = {"skipped": "several groups"}
    elif n_chunks == 1:
        report["verdict"] = _verdict(g)
    else:
        # the verdict reads both bands whole: not in a run whose memory is bounded by
        # --chunk-rows
        log.info("no verdict: the sets are larger than --chunk-rows (%d chunks) and the verdict "
                 "reads each band whole; raise --chunk-rows to get one", n_chunks)
        report["verdict"] = {"skipped": f"{n_chunks} chunks"}
    report_path = Path(g["report"]) if g["report"] else Path(target_ms + ".hitops-calibrate.json")
    report_path.write_text(json.dumps(report, indent=1))
    # ---- issue 13 (hitops/io/convert.py): the input conversions in the report, --export-uvfits
    if g["opts"].caltable:
        report["caltable"] = _write_caltable(g, result[4])
        report_path.write_text(json.dumps(report, indent=1))
    from ..io.convert import finish_report
    if finish_report(report, g["opts"], ref_ms, target_ms, outputs, g["methods"]):
        report_path.write_text(json.dumps(report, indent=1))
    # ---- end issue 13
    elapsed = time.perf_counter() - started
    log.info("wrote %s to %s; report %s; %.2f s (%s)", ", ".join(outputs.values()), target_ms,
             report_path, elapsed, ", ".join(f"{k} {v:.2f}" for k, v in g["timings"].items()))
    warnings = [report["offset_step"]["warning"]] if "offset_step" in report else \
        [e["offset_step"]["warning"] for e in report.get("groups", [])]
    for warning in dict.fromkeys(w for w in warnings if w):
        log.warning(warning)
    report["report_path"] = str(report_path)
    return report


def _no_offset_step(g, offsets, setup):
    """The warning of a run that wrote PWC/CWU without the n0 step (None otherwise)."""
    written = [g["outputs"][m] for m in ("pwc", "cwu") if m in g["outputs"]]
    if not written or g["eps"] == 0.0 or offsets is not None:
        return None
    per = ("antenna (closure phases are right, the phases themselves are not)"
           if setup is not None and setup.tracker == "antenna" else "baseline")
    return (f"{' and '.join(written)} carr{'y' if len(written) > 1 else 'ies'} a constant "
            f"2 pi eps n0 per {per} and scan (or tracking segment): no n0 offset step ran. Before "
            "imaging, run the offset step (--offset-model point, or a model column; "
            "--offset-reference-column) or self-calibrate; imaged as it is, CLEAN can diverge "
            "(docs/calibrate.md, 'The n0 offset step')")


def _write_caltable(g: Dict, tracker) -> Dict:
    """--caltable: the antenna tracker's gains as a CASA G Jones table (hitops/calibrate/gains.py)."""
    from ..io.caltable import write_gain_table
    from .gains import antenna_gain_phases

    match = g["match"]
    phase, valid = antenna_gain_phases(tracker.antenna_phase, tracker.antenna_segment,
                                       match.scan_of_time, g["ratio"], g["eps"],
                                       offsets=g.get("_offset_antennas"))
    # the cross hands of the column are transferred per baseline: the table holds the
    # parallel hands' antenna gains, from which CASA forms every correlation
    path = write_gain_table(g["opts"].caltable, g["target_ms"], match.times, phase, valid,
                            match.corr_names, overwrite=bool(g["opts"].overwrite))
    n_valid = int(valid.sum())
    log.info("wrote the antenna gains to %s (CASA G Jones, %d times x %d antennas; %d "
             "solutions, %d flagged)", path, phase.shape[0], phase.shape[1], n_valid,
             int(valid.size - n_valid))
    return {"path": str(path), "solutions": n_valid, "flagged": int(valid.size - n_valid)}


def _verdict(g: Dict) -> Dict:
    """Will FPT help here?  The prediction per baseline (hitops/calibrate/verdict.py)."""
    from .verdict import log_verdict, predict, summary

    opts = g["opts"]
    started = time.perf_counter()
    try:
        verdict = predict(g["ref_ms"], g["target_ms"], g["ratio"], opts.ref_column,
                          opts.target_column, float(opts.verdict_interval))
    except HitopsError as err:   # the columns are written: say why there is no verdict
        log.warning("no verdict: %s", err)
        return {"error": str(err)}
    log_verdict(verdict, methods_transfer_baselines=opts.tracker != "antenna",
                has_model=bool(opts.ref_model_column))
    g["timings"]["verdict"] = time.perf_counter() - started
    return {**verdict.as_dict(), "summary": summary(verdict)}


def _log_tracking(rep: Dict, setup, resolved: bool = False) -> None:
    """Confidence numbers per baseline (and antenna), and what is unresolved."""
    for e in rep["baselines"]:
        log.info("tracking %s: %d suspected slips (%d samples), %d bridged gaps, %d segments "
                 "(%d after long gaps), %d jumps%s", e["baseline"], e["suspected_slips"],
                 e["suspect_samples"], e["bridged_gaps"], e["segments"], e["long_gap_segments"],
                 e["jumps"], "".join(f"; jump {j['correlation']} at +{j['time_from_start_s']:.0f} s "
                                     f"({j['size_deg']:.0f} deg)" for j in e["jump_list"][:5]))
    for e in rep.get("antennas", []):
        log.info("tracking antenna %s: %d suspected slips, %d bridged gaps, %d segments (%d after "
                 "long gaps), %d jumps%s", e["antenna"], e["suspected_slips"], e["bridged_gaps"],
                 e["segments"], e["long_gap_segments"], e["jumps"],
                 "".join(f"; jump {j['correlation']} at +{j['time_from_start_s']:.0f} s "
                         f"({j['size_deg']:.0f} deg)" for j in e["jump_list"][:5]))
    if setup.tracker == "smooth" and resolved:
        n_seg = sum(e["long_gap_segments"] + e["jumps"] for e in rep["baselines"])
        if n_seg:
            log.info("%d segment(s) after long gaps or jumps: their wrap offsets were resolved "
                     "by the offset step per segment (see offset_step in the report)", n_seg)
    elif setup.tracker == "smooth":
        unresolved = [e for e in rep["baselines"]
                      if e["long_gap_segments"] or (e["jumps"] and setup.jump_action == "segment")]
        if unresolved:
            log.warning("%d baseline(s) have segments after long gaps or jumps whose wrap offset "
                        "is a best guess (not resolved): %s; use --tracker antenna (n0 per "
                        "antenna, closes) or --jump-action flag, or check them against a "
                        "reference", len(unresolved),
                        ", ".join(f"{e['baseline']} ({e['long_gap_segments']} gaps, "
                                  f"{e['jumps']} jumps)" for e in unresolved[:10]))
    elif setup.tracker == "antenna":
        n_seg = sum(e["long_gap_segments"] + e["jumps"] for e in rep.get("antennas", []))
        if n_seg:
            log.warning("%d antenna segment(s) start after long gaps or jumps: their wrap offset "
                        "is per antenna (closure phases are unaffected; an antenna-based phase "
                        "calibration per segment absorbs it)", n_seg)


def _merge_carry(carry, bls, part):
    carry.last_phase[bls] = part.last_phase
    carry.has_last[bls] = part.has_last
    carry.count[bls] = part.count


def _write_chunk(tx, ch, phasor_rows, calibrated, codes, io_scheduler):
    """Stage one chunk: each method's output and the new flags (FLAG | FLAG_ROW | not calibrated)."""
    from ..kernels import fpt

    names = {v: k for k, v in fpt.METHOD_CODES.items()}
    new_flag = ch["tgt_flag"] | ch["tgt_flag_row"][:, None, None] | ~calibrated[:, None, :]
    tx.write_chunk(ch["tgt_rows"], ch["tgt_data"], {names[c]: phasor_rows[c] for c in codes},
                   new_flag, io_scheduler)
