"""``hitops calibrate``: frequency phase transfer between two Measurement Sets.

One run goes down the stages of :mod:`hitops.calibrate.stages` (docs/architecture.md):

1. options: the sections (input, tracking, n0, output, run) as one
   ``CalibrateOptions``; the mode (visibilities, table, calibrator) and what it
   refuses (:mod:`~hitops.calibrate.modes`);
2. prepare: output files checked, UVFITS / FITS-IDI inputs converted
   (:mod:`~hitops.calibrate.files`), paths, subtables, write access and locks
   (:mod:`hitops.io.access`), the columns each band reads
   (:mod:`~hitops.calibrate.inputs`);
3. plan: both sets' metadata, the group pairs, the chunks
   (:mod:`~hitops.calibrate.plan`);
4. chunk loop: per chunk read -> track -> transfer -> stage
   (:mod:`~hitops.calibrate.pipeline`, the n0 step of :mod:`~hitops.calibrate.n0`,
   the calibrator step of :mod:`~hitops.calibrate.phaseref`), every group into one
   :class:`~hitops.calibrate.output.OutputTransaction`;
5. commit, once for every group;
6. report: the summary, the verdict, the JSON report (:mod:`~hitops.calibrate.report`).

The table mode (``--reference-table``) runs stages 3-6 in
:mod:`~hitops.calibrate.from_table`.

Output flags: FLAG is backed up once into FLAG_HITOPS_BACKUP (the first time
hitops writes to the set), then FLAG becomes FLAG | FLAG_ROW | (samples that
could not be calibrated).  See docs/calibrate.md.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import time
from dataclasses import dataclass
from typing import Dict, List

from ..errors import InputError
from ..io import access, flag_versions
from ..io import read as msio
from ..io.msv4.store import is_processing_set
from ..options import flat_entry, section_classes
from .band_index import INDEX_COLUMNS
from .from_table import calibrate_from_table
from .inputs import CalibrateOptions, check_inputs, output_columns, parse_methods
from .modes import Mode, check_options
from .output import drop_stale_columns
from .files import PreparedInputs, prepare_inputs

log = logging.getLogger("hitops.calibrate")

#: the option sections of hitops/schemas/calibrate.yml, each a frozen dataclass
InputOptions = section_classes("calibrate")["input"]
TrackingOptions = section_classes("calibrate")["tracking"]
N0Options = section_classes("calibrate")["n0"]
OutputOptions = section_classes("calibrate")["output"]
RunOptions = section_classes("calibrate")["run"]


@dataclass(frozen=True)
class RunStart:
    """What stages 1-2 hand to the run: the options (REF_MS and TARGET_MS as the
    Measurement Sets they became), the methods, the mode, the conversions, the start time."""

    opts: CalibrateOptions
    methods: List[str]
    mode: Mode
    prepared: PreparedInputs
    started: float

    @property
    def ref_ms(self) -> str:
        return self.opts.ref_ms

    @property
    def target_ms(self) -> str:
        return self.opts.target_ms


def calibrate(ref_ms, target_ms, input: InputOptions = InputOptions(),
              tracking: TrackingOptions = TrackingOptions(), n0: N0Options = N0Options(),
              output: OutputOptions = OutputOptions(), run: RunOptions = RunOptions()) -> Dict:
    """Frequency phase transfer from ``ref_ms`` (reference band) to ``target_ms``.

    Writes one column per method into ``target_ms`` (PWC_DATA, CFPT_DATA,
    CWU_DATA by default) holding V_target * exp(-i*(R*phi_cal - 2*pi*eps*n))
    (PWC; CFPT and CWU analogues), updates FLAG (backed up once into
    FLAG_HITOPS_BACKUP) and writes a JSON report (default
    ``<target_ms>.hitops-calibrate.json``).  Returns the report as a dict.

    The options come in sections, each a frozen dataclass of
    hitops/schemas/calibrate.yml (defaults: the schema's):
    ``input`` (columns, ratio, stations, time tolerance, ``reference_table``,
    ``calibrator_field``, ``restore_flags``, ``workdir``), ``tracking`` (``tracker``:
    count, smooth or antenna, and what tunes the robust ones: docs/tracking.md),
    ``n0`` (the offset step), ``output`` (``method``, columns, flag version, report,
    ``export_uvfits``, ``caltable``) and ``run`` (memory, scheduler, locks, verdict),
    e.g. ``calibrate(ref, tgt, tracking=TrackingOptions(tracker="antenna"),
    output=OutputOptions(method="pwc,cfpt"))``.  :func:`calibrate_flat` takes the
    command line's flags by name instead.
    """
    started = time.perf_counter()
    # ---- stage 1: options
    opts = CalibrateOptions(ref_ms, target_ms, input, tracking, n0, output, run)
    methods = parse_methods(output.method)
    mode = check_options(opts, methods)
    # ---- stage 2: prepare. The output files checked, UVFITS / FITS-IDI inputs converted
    # once into Measurement Sets in --workdir, before anything is written
    prepared = prepare_inputs(opts)
    # a Measurement Set v2 or an MSv4 processing set (hitops/io/msv4/), by what the path holds
    ref_ms = msio.check_ms(prepared.ref_ms, "reference-band Measurement Set", True)
    target_ms = msio.check_ms(prepared.target_ms, "target-band Measurement Set", True)
    if os.path.realpath(ref_ms) == os.path.realpath(target_ms):
        raise InputError(f"REF_MS and TARGET_MS are the same set ({ref_ms}); give the "
                         "reference-band and the target-band Measurement Sets")
    access.require_subtables(ref_ms, "reference-band Measurement Set")
    access.require_subtables(target_ms, "target-band Measurement Set")
    access.require_writable(target_ms, "target-band Measurement Set")
    start = RunStart(dataclasses.replace(opts, ref_ms=ref_ms, target_ms=target_ms), methods,
                     mode, prepared, started)
    # one hitops run per target set at a time; then casacore's own locks, whose wait
    # would otherwise be silent and unbounded (hitops/io/access.py)
    lock_timeout = run.lock_timeout
    with access.RunLock(target_ms, lock_timeout, "target-band Measurement Set"):
        access.wait_for_table_lock(target_ms, True, lock_timeout, "target-band Measurement Set")
        access.wait_for_table_lock(ref_ms, False, lock_timeout, "reference-band Measurement Set")
        if not is_processing_set(target_ms):   # a store's writer removes its own leftovers
            drop_stale_columns(target_ms)
        try:
            _restore_flags(start.opts)
            # the mode decides the path: the table mode reads no reference visibilities
            result = (calibrate_from_table(start) if mode is Mode.TABLE
                      else _calibrate_visibilities(start))
            _save_flags(start.opts, methods)
            return result
        except RuntimeError as err:
            # casacore's messages do not always say which table failed: find the damage
            read = [(ref_ms, [input.ref_column, "FLAG"] + INDEX_COLUMNS),
                    (target_ms, [input.target_column, "FLAG"] + INDEX_COLUMNS)]
            access.raise_if_damaged(err, read + ([(input.reference_table, None)]
                                                 if input.reference_table else []))
            raise
        finally:
            # dask-ms keeps its table handles until they are collected; close them now, so
            # that CASA (its own casacore) or another process can change the set next
            # without this process holding a stale column list
            gc.collect()


#: ``hitops calibrate`` with one keyword per flag (the command line's form; the CLI and
#: Stimela's cab call it through hitops/calibrate/app.py): the sections are made from them
calibrate_flat = flat_entry("calibrate", calibrate)


def _restore_flags(opts: CalibrateOptions) -> None:
    """--restore-flags: FLAG set to the union of the named flag versions (all of them
    read and checked before FLAG is written: a missing one is refused with FLAG as it was)."""
    names = flag_versions.split_names(opts.input.restore_flags)
    if names:
        flag_versions.restore_versions(opts.target_ms, names)


def _save_flags(opts: CalibrateOptions, methods: List[str]) -> None:
    """--save-flags: the run's FLAG kept as a CASA flag version, its comment saying what made it."""
    if opts.output.save_flags:
        columns = ", ".join(output_columns(opts, methods).values())
        flag_versions.save_version(
            opts.target_ms, opts.output.save_flags,
            f"after hitops calibrate --method {opts.output.method} -> {columns} (started from "
            f"{opts.input.restore_flags or 'FLAG'})")


def _calibrate_visibilities(start: RunStart) -> Dict:
    """Stages 2 (the columns) to 6 of the visibility and calibrator modes, holding the
    target set's run lock."""
    import dask

    from .plan import build_plan
    from .skeleton import run_source
    from .visibility_source import VisibilitySource

    outputs, columns = check_inputs(start.opts, start.methods, start.ref_ms, start.target_ms)
    timings = {"checks": time.perf_counter() - start.started}
    # every dask computation of the run, dask-ms's own included, runs on this process's
    # threads unless --scheduler names a cluster: a dask.distributed Client that the caller
    # made the default must not receive the reads of a run that did not ask for it
    with dask.config.set(scheduler="threads"):
        plan = build_plan(start.opts, start.methods, outputs, start.ref_ms, start.target_ms,
                          columns, timings)
        # --scheduler: an address, or slurm[:N] (dask-jobqueue worker jobs): hitops/cluster.py
        from ..cluster import scheduler_client
        with scheduler_client(start.opts.run.scheduler) as client:
            # stages 4-6: the run skeleton with REF_MS's visibilities as its source
            return run_source(VisibilitySource.of(plan, client, start.started, start.prepared))
