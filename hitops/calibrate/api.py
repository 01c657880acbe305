"""``hitops calibrate``: frequency phase transfer between two Measurement Sets.

The pipeline, one module per stage (docs/architecture.md):

1. :mod:`~hitops.calibrate.inputs`: every option checked against both sets
   before anything is read or written;
2. :mod:`~hitops.calibrate.plan`: both bands opened through dask-ms, their
   (field, spectral window) groups paired, and per pair the stations,
   correlations and times matched, the chunks cut and checked, R split into
   r + eps and the tracker set up;
3. :mod:`~hitops.calibrate.pipeline`: per chunk read -> track -> transfer ->
   write (with the n0 offset step of :mod:`~hitops.calibrate.n0`
   between a first and a writing pass), every group into one
   :class:`~hitops.calibrate.output.OutputTransaction`, committed once;
4. :mod:`~hitops.calibrate.report`: the summary, the verdict, the JSON report.

Output flags: FLAG is backed up once into FLAG_HITOPS_BACKUP (the first time
hitops writes to the set), then FLAG becomes FLAG | FLAG_ROW | (samples that
could not be calibrated).  See docs/calibrate.md.
"""

from __future__ import annotations

import gc
import logging
import os
import time
from typing import TYPE_CHECKING, Dict, List

from ..errors import InputError
from ..io import access, flag_versions
from ..io import read as msio
from ..options import make_options
from .band_index import INDEX_COLUMNS
from .from_table import calibrate_from_table
from .inputs import CalibrateOptions, check_inputs, output_columns, parse_methods
from .commit import stage_and_commit
from .output import (FLAG_BACKUP, OutputTransaction, drop_stale_columns,
                     release_cluster_tables)
from .rules import PreparedInputs, prepare_inputs

if TYPE_CHECKING:   # the plan's modules load dask-ms: imported where a run starts
    from .plan import RunPlan

log = logging.getLogger("hitops.calibrate")


def calibrate(ref_ms, target_ms, method="pwc", ref_column="DATA", target_column="DATA",
              ref_model_column=None, offset_reference_column=None, offset_model=None,
              max_offset_wraps=50, offset_ambiguity_deg=2.0, ratio=None, antenna_map=None, output_column=None,
              overwrite=False, average_channels=False, time_tolerance=None, tracker="count",
              workdir=None, export_uvfits=None, reference_table=None,
              half_window=0, coherence_time=20.0, snr=0.0, max_gap=-1, jump_threshold=-1.0,
              jump_window=0, jump_action="segment", refant=None, solve_half_window=-1,
              no_elevation_scaling=False, memory_budget="auto", chunk_rows=0, report=None, scheduler=None,
              lock_timeout=60.0, no_verdict=False, verdict_interval=60.0, caltable=None,
              calibrator_field=None, calibrator_model_column=None, restore_flags=None, save_flags=None) -> Dict:
    """Frequency phase transfer from ``ref_ms`` (reference band) to ``target_ms``.

    Writes one column per method into ``target_ms`` (PWC_DATA, CFPT_DATA,
    CWU_DATA by default) holding V_target * exp(-i*(R*phi_cal - 2*pi*eps*n))
    (PWC; CFPT and CWU analogues), updates FLAG (backed up once into
    FLAG_HITOPS_BACKUP) and writes a JSON report (default
    ``<target_ms>.hitops-calibrate.json``).  Returns the report as a dict.

    ``tracker`` picks the reference wrap tracker: ``count`` (the paper's
    step > pi rule), ``smooth`` or ``antenna`` (:mod:`hitops.tracking`,
    docs/tracking.md); the options after it tune the robust trackers.
    ``reference_table``: antenna phases from a table solved on ``ref_ms`` (from_table.py).
    """
    started = time.perf_counter()
    # ---- 1. inputs, all checked before anything is written
    methods = parse_methods(method)
    # the output files checked, UVFITS / FITS-IDI inputs converted once into Measurement
    # Sets in --workdir, before anything is written (hitops/calibrate/rules.py)
    prepared = prepare_inputs(ref_ms, target_ms, workdir, export_uvfits, overwrite,
                              caltable=caltable, tracker=tracker,
                              reference_table=reference_table)
    ref_ms, target_ms = prepared.ref_ms, prepared.target_ms
    ref_ms = msio.check_ms(ref_ms, "reference-band Measurement Set")
    target_ms = msio.check_ms(target_ms, "target-band Measurement Set")
    _check_run_scalars(ref_ms, target_ms, lock_timeout, verdict_interval)
    access.require_subtables(ref_ms, "reference-band Measurement Set")
    access.require_subtables(target_ms, "target-band Measurement Set")
    access.require_writable(target_ms, "target-band Measurement Set")
    # one hitops run per target set at a time; then casacore's own locks, whose wait
    # would otherwise be silent and unbounded (hitops/io/access.py)
    with access.RunLock(target_ms, lock_timeout, "target-band Measurement Set"):
        access.wait_for_table_lock(target_ms, True, lock_timeout, "target-band Measurement Set")
        access.wait_for_table_lock(ref_ms, False, lock_timeout, "reference-band Measurement Set")
        drop_stale_columns(target_ms)
        # the sets as converted and checked; every other option as given
        opts = make_options("calibrate", dict(
            ref_ms=ref_ms, target_ms=target_ms, method=method, ref_column=ref_column,
            target_column=target_column, ref_model_column=ref_model_column,
            offset_reference_column=offset_reference_column, offset_model=offset_model,
            max_offset_wraps=max_offset_wraps, offset_ambiguity_deg=offset_ambiguity_deg,
            ratio=ratio, antenna_map=antenna_map, output_column=output_column,
            overwrite=overwrite, average_channels=average_channels,
            time_tolerance=time_tolerance, tracker=tracker, half_window=half_window,
            coherence_time=coherence_time, no_elevation_scaling=no_elevation_scaling, snr=snr,
            max_gap=max_gap, jump_threshold=jump_threshold, jump_window=jump_window,
            jump_action=jump_action, refant=refant, solve_half_window=solve_half_window,
            memory_budget=memory_budget, chunk_rows=chunk_rows, report=report,
            workdir=workdir, export_uvfits=export_uvfits, scheduler=scheduler,
            lock_timeout=lock_timeout, caltable=caltable, no_verdict=no_verdict,
            verdict_interval=verdict_interval, calibrator_field=calibrator_field,
            calibrator_model_column=calibrator_model_column, reference_table=reference_table, restore_flags=restore_flags,
            save_flags=save_flags))
        run = calibrate_from_table if opts.reference_table else _calibrate_locked
        try:
            _restore_flags(opts, target_ms)
            result = run(opts, methods, ref_ms, target_ms, started, prepared)
            _save_flags(opts, methods, target_ms)
            return result
        except RuntimeError as err:
            # casacore's messages do not always say which table failed: find the damage
            read = [(ref_ms, [ref_column, "FLAG"] + INDEX_COLUMNS),
                    (target_ms, [target_column, "FLAG"] + INDEX_COLUMNS)]
            access.raise_if_damaged(err, read + ([(reference_table, None)] if reference_table
                                                 else []))
            raise
        finally:
            # dask-ms keeps its table handles until they are collected; close them now, so
            # that CASA (its own casacore) or another process can change the set next
            # without this process holding a stale column list
            gc.collect()


def _restore_flags(opts: CalibrateOptions, target_ms: str) -> None:
    """--restore-flags: FLAG set to the union of the named flag versions (all of them
    read and checked before FLAG is written: a missing one is refused with FLAG as it was)."""
    names = flag_versions.split_names(opts.restore_flags)
    if names:
        flag_versions.restore_versions(target_ms, names)


def _save_flags(opts: CalibrateOptions, methods: List[str], target_ms: str) -> None:
    """--save-flags: the run's FLAG kept as a CASA flag version, its comment saying what made it."""
    if opts.save_flags:
        columns = ", ".join(output_columns(opts, methods).values())
        flag_versions.save_version(
            target_ms, opts.save_flags, f"after hitops calibrate --method {opts.method} -> "
            f"{columns} (started from {opts.restore_flags or 'FLAG'})")


def _check_run_scalars(ref_ms: str, target_ms: str, lock_timeout, verdict_interval) -> None:
    """Two different sets, a usable lock timeout and verdict interval: one line each."""
    if os.path.realpath(ref_ms) == os.path.realpath(target_ms):
        raise InputError(f"REF_MS and TARGET_MS are the same set ({ref_ms}); give the "
                         "reference-band and the target-band Measurement Sets")
    if not float(lock_timeout) >= 0:
        raise InputError(f"--lock-timeout {lock_timeout} must be >= 0 seconds")
    if not float(verdict_interval) > 0:
        raise InputError(f"--verdict-interval {verdict_interval} must be a positive number of "
                         "seconds (e.g. 60)")


def _calibrate_locked(opts: CalibrateOptions, methods: List[str], ref_ms: str, target_ms: str,
                      started: float, prepared: PreparedInputs) -> Dict:
    """The rest of :func:`calibrate`, holding the target set's run lock: plan, run, report."""
    import dask

    # every dask computation of the run, dask-ms's own included, runs on this process's
    # threads unless --scheduler names a cluster: a dask.distributed Client that the caller
    # made the default must not receive the reads of a run that did not ask for it
    with dask.config.set(scheduler="threads"):
        return _plan_and_run(opts, methods, ref_ms, target_ms, started, prepared)


def _plan_and_run(opts: CalibrateOptions, methods: List[str], ref_ms: str, target_ms: str,
                  started: float, prepared: PreparedInputs) -> Dict:
    from .plan import build_plan

    outputs, columns = check_inputs(opts, methods, ref_ms, target_ms)
    timings = {"checks": time.perf_counter() - started}
    run = build_plan(opts, methods, outputs, ref_ms, target_ms, columns, timings)
    client = closer = None
    if opts.scheduler:
        # an address, or slurm[:N] (dask-jobqueue worker jobs): hitops/cluster.py
        from ..cluster import dask_client
        client, closer = dask_client(opts.scheduler)
    try:
        return _run(run, client, started, prepared)
    finally:
        if closer is not None:
            closer.close()


def _run(run: RunPlan, client, started: float, prepared: PreparedInputs) -> Dict:
    """Every group pair into one OutputTransaction, committed once; then the report."""
    from .phaseref import check_calibrator_field, phase_reference, settle_n0_warnings
    from .pipeline import run_group
    from .report import combined_report, group_report, write_report

    calibrator = check_calibrator_field(run)   # --calibrator-field, before anything is written

    # everything this run changes in the target set (hitops/calibrate/output.py)
    tx = OutputTransaction(run.target_ms, run.outputs, run.columns.target_data, None,
                           run.chunk_rows,
                           direct_writes=client is None and all(
                               isinstance(g.match.datasets["tgt"], msio.StorageRows)
                               for g in run.groups))
    tx.check_space()
    if client is not None:
        release_cluster_tables(client)   # stale handles of an earlier run on this cluster
    # a target not stored in time order and cut into chunks is written in scattered rows
    created = tx.create_columns(scattered=any(g.n_chunks > 1 and not g.match.tgt.time_ordered
                                              for g in run.groups))
    if client is not None:
        log.info("created %s in %s before sending work to the cluster", ", ".join(created),
                 run.target_ms)

    def stage():
        results = [run_group(run, group, tx, client) for group in run.groups]
        # the instrumental term solved on the calibrator, applied to the staged columns
        referencing = phase_reference(run, tx, calibrator)
        if client is not None:
            release_cluster_tables(client)
        return results, referencing

    results, referencing = stage_and_commit(tx, stage, lambda: _committed(run, tx))
    try:
        reports = [group_report(run, group, result, tx, started)
                   for group, result in zip(run.groups, results)]
        report = reports[0] if len(reports) == 1 else combined_report(run, reports)
        if referencing is not None:
            report["phase_referencing"] = referencing
            settle_n0_warnings(report, calibrator)
        return write_report(run, report, results[0] if len(reports) == 1 else None, started,
                            prepared, results)
    except BaseException as stop:
        # an interrupt or a failure after the commit: the set is no longer as it was, and
        # hitops/cli.py says what it holds
        stop.add_note(_committed(run, tx))
        raise


def _committed(run, tx) -> str:
    """What the target set holds after the commit, for a run stopped before its end."""
    columns = ", ".join(run.outputs.values())
    flags = (f" and the updated FLAG (the flags before hitops in {FLAG_BACKUP})"
             if tx.flag_written else "")
    after = "the report" if run.opts.no_verdict else "the verdict and the report"
    return (f"the run had finished writing: {run.target_ms} holds the new {columns}{flags}; "
            f"what follows the commit ({after}) did not finish; rerun the same command with "
            "--overwrite to redo it (the columns come out the same)")
