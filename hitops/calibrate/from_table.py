"""``hitops calibrate --reference-table``: the reference band's antenna phases from a CASA table.

Instead of tracking REF_MS's visibility phases, the antenna phases come from a
calibration table solved on REF_MS (fringefit 'Fringe Jones', gaincal 'G Jones' or
'T Jones').  :mod:`hitops.solutions` counts each antenna's wraps (the rates bridging the
solutions), re-refers reference antenna changes and transfers them per antenna and per
target channel (R_k = nu_k / nu_ref): one :class:`~hitops.solutions.transfer.TargetWindow`
per (field, target window).  This module applies them to the target's column:

    OUT_pq(k) = TARGET_pq(k) * exp(-i (theta_p(k) - theta_q(k))),

theta evaluated from those windows exactly as CASA applycal evaluates the ``--caltable``
table written from them (:mod:`hitops.solutions.apply`), so the column and applycal of
the table agree.  Being per antenna, closure phases are kept by construction.

Methods: ``pwc`` counts the wraps (theta = R_k * u, u the unwrapped solution phase, which
is the paper's PWC per channel); ``cfpt`` scales the wrapped solution phase (R_k * phi, what
a row-by-row transfer such as AIPS SNCOR 'XFER' does), for comparison; ``cwu`` is refused:
rewrapping cancels the target band's unwrap, so with the same reference wrap count it
is ``pwc`` (GUIDE section 1).  With ``--offset-model`` or ``--offset-reference-column``,
``pwc`` first solves each antenna's integer per segment (the n0 step,
:mod:`hitops.calibrate.n0.table`) in a pass over the target set.  The output column,
FLAG and the staging follow the visibility path
(:class:`~hitops.calibrate.output.OutputTransaction`: whole or not at all), and so does the
chunk loop: rows per chunk from ``--memory-budget`` (hitops/calibrate/memory.py) or
``--chunk-rows``, each chunk read on :class:`~hitops.calibrate.chunk_io.ChunkIO`'s thread
while the one before is corrected, its outputs written there too; the target's
windows, correlations and stations from its :class:`~hitops.io.metadata.SetMetadata`,
read once.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional

from ..io.metadata import SetMetadata, read_metadata
from ..io.msv4.store import is_processing_set
from ..logs import Progress
from ..solutions.api import (PreparedTransfer, TransferReport, pair_table, transfer_paired,
                             transfer_report, write_target_table)
from .chunk_io import ChunkIO
from .table_chunks import (SampleCounts, TableRun, TargetChunk, chunk_sums, correct_and_flag,
                           merge_sums, n0_column, read_chunk)
from .table_source import target_layout
from .table_store import StoreRows
from .inputs import CalibrateOptions, check_inputs
from .output import OutputTransaction
from .output_msv4 import DataGroupTransaction, data_groups_entry
from .files import PreparedInputs, record_conversions_and_export
from .run_report import (AfterCommit, AntennaWraps, RunReport, TableTracking, report_path,
                         write_run_report)
from .skeleton import run_source

log = logging.getLogger("hitops.calibrate")

#: what each method makes of the table's solution phases
WRAP_COUNTING = {"pwc": True, "cfpt": False}


def each_chunk(run: TableRun, work: Callable[[TargetChunk, ChunkIO], None],
               offset_column: Optional[str] = None, what: str = "writing pass",
               writes_apart: bool = False) -> None:
    """``work(chunk, io)`` on every chunk of the target set in order; chunk k+1 is read on
    :class:`ChunkIO`'s thread while chunk k is worked on (``io.write`` queues a write there,
    or on a thread of its own with ``writes_apart``: a processing set's new data groups).
    The pass's progress is logged (at most every 5 s) when it has several chunks."""
    progress = (Progress(f"calibrate --reference-table {what}: chunks", run.n_chunks,
                         logger=log) if run.n_chunks > 1 else None)
    with ChunkIO(lambda k: read_chunk(run, k, offset_column), run.n_chunks,
                 writes_apart=writes_apart) as io:
        for k in range(run.n_chunks):
            chunk = io.chunk(k)
            io.read_ahead(k + 1)
            work(chunk, io)
            if progress is not None:
                progress.update()


def offset_step(run: TableRun, prepared: PreparedTransfer, client=None):
    """The n0 step (hitops/calibrate/n0/table.py): a first pass over the target set,
    one lattice solve per field and receptor; the transfer with the integers taken out.
    Each chunk's sums are made on their own and added in chunk order, on this process or,
    with ``client``, on the cluster's workers (hitops/calibrate/table_workers.py): the
    same additions in the same order either way."""
    from .n0.table import apply_offsets, solve

    if client is not None:
        from .table_workers import sums_on_workers
        sums = sums_on_workers(client, run, prepared)
    else:
        sums: Dict = {}
        each_chunk(run, lambda chunk, io: merge_sums(sums, chunk_sums(run, prepared, chunk)),
                   n0_column(run), "first pass (n0 step)")
    offsets = solve(prepared, sums, run.opts.n0.max_offset_wraps,
                    list(run.tgt_meta.antennas.names), run.layout.chan_freq)
    for entry in offsets.solves:
        moved = {name: k for name, k in entry["k"].items() if k}
        log.info("n0 step (field %d, receptor %d, %s, mean cos mismatch %.3f): %s",
                 entry["field"], entry["receptor"], entry["method"], entry["mean_cos_mismatch"],
                 ", ".join(f"{n} {k:+d}" for n, k in moved.items()) or "no integer moved")
    return apply_offsets(prepared, offsets), offsets


def write_outputs(run: TableRun, tx: OutputTransaction,
                  transfers: Dict[str, PreparedTransfer], client=None) -> SampleCounts:
    """Every chunk of the target set corrected and staged (on the I/O thread, or with
    ``client`` by the cluster's workers: hitops/calibrate/table_workers.py); the counts."""
    if client is not None:
        from .table_workers import write_on_workers
        return write_on_workers(client, run, tx, transfers)
    counts = SampleCounts()
    # FLAG as read is FLAG now (it changes only at the commit): no second read to compare
    flag_is_read = run.columns.flag == "FLAG"

    def correct(chunk: TargetChunk, io: ChunkIO) -> None:
        done = correct_and_flag(run, transfers, chunk)
        io.write(tx.write_outputs, chunk.rows, done.outputs, done.new_flag, None,
                 chunk.columns["flag"] if flag_is_read else None)
        counts.add(done.before, done.new_flag)

    each_chunk(run, correct, writes_apart=tx.writes_apart)
    return counts


def _rows_per_chunk(opts: CalibrateOptions, meta: SetMetadata, n_rows: int,
                    n_methods: int) -> int:
    """--chunk-rows, else the rows --memory-budget holds (hitops/calibrate/memory.py's model
    of a chunk of both bands: the table path reads one, so it stays within the budget)."""
    from .memory import parse_budget, rows_for_budget
    from .output_msv4 import transaction_class

    if int(opts.run.chunk_rows) > 0:
        return int(opts.run.chunk_rows)
    budget = parse_budget(opts.run.memory_budget)
    explicit = str(opts.run.memory_budget or "auto").strip().lower() != "auto"
    n_chan = max([w.num_chan for w in meta.windows] or [1])
    n_corr = max([len(p.corr_types) for p in meta.polarizations] or [1])
    # a processing set's outputs are written beside the next read (hitops/calibrate/chunk_io.py)
    rows = rows_for_budget(budget, n_rows, n_corr, n_chan, n_methods, strict=explicit,
                           local=True, writes_apart=transaction_class(meta.ms).writes_apart)
    log.info("memory budget %.0f MB: up to %d target rows per chunk (--chunk-rows overrides)",
             budget / 1e6, rows)
    return max(1, rows)


def plan_table_run(opts: CalibrateOptions, methods: List[str], ref_ms: str,
                   target_ms: str) -> TableRun:
    """Every check of the target set (the options were checked in hitops/calibrate/modes.py);
    the chunks."""
    from ..io.read import row_count

    outputs, columns = check_inputs(opts, methods, ref_ms, target_ms)
    meta = read_metadata(target_ms)
    n_rows = row_count(target_ms)
    chunk_rows = _rows_per_chunk(opts, meta, n_rows, len(methods))
    store = (StoreRows.of(target_ms, [columns.target_data], chunk_rows)
             if is_processing_set(target_ms) else None)
    return TableRun(opts, methods, target_ms, outputs, columns, meta, target_layout(meta),
                    n_rows, chunk_rows, store)


def _tracking(report: TransferReport) -> TableTracking:
    """What the run tracked: each antenna's wraps counted in the first method's solutions."""
    return TableTracking(
        tuple(AntennaWraps(a.name, a.n_wraps, a.n_flagged, a.n_solutions, a.max_residual_rad)
              for a in report.antennas), report.n_segments, report.wrap_counting)


def _sections(run: TableRun, ref_ms: str, transfers: Dict[str, PreparedTransfer],
              counts: SampleCounts, offsets, started: float) -> Dict:
    """The table path's report sections (the run report's, hitops/calibrate/run_report.py)."""
    first = transfers[run.methods[0]]
    reports = {m: transfer_report(p, None, 0) for m, p in transfers.items()}
    sections = {
        "ref_ms": ref_ms, "target_ms": run.target_ms, "methods": run.methods,
        "outputs": run.outputs, "chunks": run.n_chunks,
        "reference_table": {"path": first.table.path, "kind": first.table.kind,
                            "methods": {m: dataclasses.asdict(r) for m, r in reports.items()}},
        "samples": dataclasses.asdict(counts),
        "tracking": _tracking(reports[run.methods[0]]).as_json(),
        "timings_s": {"total": round(time.perf_counter() - started, 4)},
    }
    if offsets is not None:
        sections["offsets"] = {"compared_with": run.columns.offset, "solves": offsets.solves}
    return sections


def calibrate_from_table(start) -> Dict:
    """Stages 2 (the columns) to 6 of the table mode (``--reference-table``; its options
    refused in hitops/calibrate/modes.py): checks, transfer, column, table, report (the run
    skeleton, hitops/calibrate/skeleton.py, with the table as its source).  ``start``: the
    run's :class:`hitops.calibrate.api.RunStart`.  With ``--scheduler`` (a processing set
    target: modes.py refuses it on a v2 one) the cluster's workers read, correct and write
    the chunks."""
    run = plan_table_run(start.opts, start.methods, start.ref_ms, start.target_ms)
    # every check of the table (type, set, stations, solution interval) before anything
    # is written or a cluster is reached
    paired = pair_table(start.opts.input.reference_table, start.ref_ms, start.target_ms,
                        antenna_map=start.opts.input.antenna_map, target_meta=run.tgt_meta)
    from ..cluster import scheduler_client
    with scheduler_client(start.opts.run.scheduler) as client:
        return run_source(TableSource.of(start, run, paired, client))


@dataclass(frozen=True)
class TableSource:
    """A planned ``--reference-table`` run: the transfer of every method, checked, and the
    n0 step's integers taken out (its first pass done); nothing written yet."""

    run: TableRun
    ref_ms: str
    transfers: Dict[str, PreparedTransfer]
    offsets: object             # n0/table.TableOffsets, None without the n0 step
    started: float
    prepared: PreparedInputs
    client: object = None       # a dask.distributed Client (--scheduler), else None

    @classmethod
    def of(cls, start, run: TableRun, paired, client=None) -> "TableSource":
        """The table source of a run's :class:`hitops.calibrate.api.RunStart`, its
        :class:`TableRun` and the table paired with the sets (``pair_table``)."""
        transfers = {m: transfer_paired(paired, wrap_counting=WRAP_COUNTING[m])
                     for m in start.methods}
        offsets = None
        if run.columns.offset and "pwc" in transfers:   # --offset-model / --offset-reference-column
            transfers["pwc"], offsets = offset_step(run, transfers["pwc"], client)
        return cls(run, start.ref_ms, transfers, offsets, start.started, start.prepared, client)

    def open_transaction(self) -> OutputTransaction:
        run = self.run
        if run.store is not None:   # a processing set: a data group per method
            tx = DataGroupTransaction(run.target_ms, run.outputs, run.columns.target_data,
                                      list(run.store.sources), run.chunk_rows,
                                      bool(run.opts.output.overwrite))
        else:
            tx = OutputTransaction(run.target_ms, run.outputs, run.columns.target_data,
                                   run.n_rows, run.chunk_rows, direct_writes=True)
        tx.check_space()
        tx.create_columns()
        return tx

    def stage(self, tx: OutputTransaction) -> SampleCounts:
        return write_outputs(self.run, tx, self.transfers, self.client)

    def after_commit(self) -> str:
        return "the report and --caltable" if self.run.opts.output.caltable else "the report"

    def report(self, tx: OutputTransaction, counts: SampleCounts) -> Dict:
        return _finish(self.run, self.ref_ms, self.transfers, counts, self.offsets,
                       self.started, self.prepared, data_groups_entry(tx))


def _finish(run: TableRun, ref_ms: str, transfers: Dict[str, PreparedTransfer],
            counts: SampleCounts, offsets, started: float, prepared: PreparedInputs,
            data_groups: Optional[Dict]) -> Dict:
    """After the commit: --caltable, --export-uvfits, the report written once
    (``data_groups``: where a processing set's results are, else None)."""
    opts, method = run.opts, run.methods[0]
    log.info("%d of %d target samples not calibrated by the table (no unflagged solution on "
             "either side), %d flagged before", counts.not_calibrated, counts.n_samples,
             counts.flagged_before)
    sections = _sections(run, ref_ms, transfers, counts, offsets, started)
    if data_groups is not None:
        sections["data_groups"] = data_groups
    report = RunReport(report_path(opts, run.target_ms), sections,
                       AfterCommit(verdict={"skipped": "reference table: no reference-band "
                                                       "visibilities are read"}))

    def caltable() -> Dict:
        n_rows = write_target_table(transfers[method], opts.output.caltable, bool(opts.output.overwrite))
        log.info("wrote the target-band Fringe Jones table %s (%d rows, %s)", opts.output.caltable,
                 n_rows, method)
        return {"path": str(opts.output.caltable), "kind": "Fringe Jones", "rows": n_rows,
                "method": method}

    body = write_run_report(
        report, caltable if opts.output.caltable else None,
        lambda after: record_conversions_and_export(after, opts, ref_ms, run.target_ms,
                                                    run.outputs, run.methods, prepared))
    log.info("wrote %s to %s from reference table %s; report %s; %.2f s",
             ", ".join(run.outputs.values()), run.target_ms, opts.input.reference_table, report.path,
             time.perf_counter() - started)
    return body
