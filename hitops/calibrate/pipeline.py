"""Stage 4 of ``hitops calibrate``, the chunk loop of one group pair: read -> track -> transfer -> stage.

For each time chunk of the plan, in time order:

1. read both bands (:func:`hitops.calibrate.chunk_read.read_chunk`);
2. track the reference wraps through the tracker's one interface
   (:class:`hitops.tracking.base.WrapTracker`: ``track_chunk`` ->
   :class:`~hitops.tracking.base.ChunkTracking`, one share per baseline batch,
   ``absorb`` and ``finish_chunk``): the smooth and antenna trackers track the
   whole chunk here with their context; the count tracker's share counts
   inside each group's task from a carried sample;
3. transfer: :func:`hitops.calibrate.transfer.transfer_batch` on baseline batches
   (:class:`hitops.calibrate.batch_tasks.BatchTasks`: threads, or a dask cluster; a
   :class:`~hitops.calibrate.transfer.TransferInputs` in, a
   :class:`~hitops.calibrate.transfer.TransferResult` out; the numba kernels of
   :mod:`hitops.kernels.fpt`);
4. write the outputs and new flags through the run's
   :class:`hitops.calibrate.output.OutputTransaction`.

Reads and writes run on one I/O thread (:class:`hitops.calibrate.chunk_io.ChunkIO`):
chunk k+1 is read while chunk k's kernels run, and chunk k is written while chunk
k+1's run (a processing set's outputs on a thread of their own).  Steps 2-3 of one
chunk are :meth:`GroupPipeline.advance`, from the :class:`PassState` the previous
chunk carried out: the same method runs in the chunk tasks of
hitops/calibrate/worker_chunks.py, where the workers read and write.

With the n0 offset step a first pass (steps 1-3) sums the calibrated phase against the offset
reference per scan or segment (per target channel across a window); the integers are solved
(:mod:`hitops.calibrate.n0.step`) and the writing pass follows (hitops/calibrate/passes.py
runs the passes).  With a segmented tracker (smooth, antenna) the first pass keeps its output
when it fits in a fifth of the memory budget, and the writing pass (hitops/calibrate/kept.py)
only shifts it by 2 pi eps k
per segment (:func:`hitops.calibrate.n0.step.offset_shifted_rows`) instead of tracking and
transferring again.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from ..logs import Progress
from ..kernels.segments import SegmentSums, segment_row_sums
from ..tracking.base import ChunkTracking, WrapTracker
from ..tracking.count import Carry
from ..tracking.factory import new_tracker
from .chunk_io import ChunkIO
from .chunk_read import ChunkData, read_chunk
from .batch_tasks import BatchTasks, StartedGroups
from .kept import KeptChunk
from .n0.step import OffsetSums, channel_sums
from .output import OutputTransaction
from .row_outputs import PlacedGroup, RowOutputs, rows_of_batches
from .plan import GroupPlan, RunPlan
from .transfer import SampleCounts, TransferInputs, batch_rows, plan_groups

log = logging.getLogger("hitops.calibrate")


@dataclass
class PassResult:
    """What one pass over the chunks adds up."""

    samples: SampleCounts
    tracker: WrapTracker                        # the pass's tracker, after its last chunk
    sums: OffsetSums                            # what the n0 step needs of the pass

    @property
    def wrap_events(self) -> np.ndarray:
        """(n_bl, n_corr) wrap events of the pass."""
        return self.tracker.stats.per_series["wrap_events"].copy()

    @property
    def jump_flagged(self) -> int:
        """Reference samples flagged after a jump (--jump-action flag)."""
        return int(self.tracker.stats.per_series["jump_flagged"].sum())


@dataclass
class StartedTransfer:
    """A chunk's baseline-group tasks, started, and where each group's output goes."""

    placed: List[PlacedGroup]
    groups: StartedGroups


@dataclass(frozen=True)
class PassSpec:
    """What one pass does at every chunk: ``offsets`` per-scan n0 shifts (count) and
    ``offset_k`` their integers (a per-channel transfer's delays need them); ``segment_k``
    per-segment integers (segmented trackers); ``write`` the outputs (False: a first pass)."""

    offsets: Optional[np.ndarray] = None
    segment_k: Optional[Dict[tuple, int]] = None
    offset_k: Optional[np.ndarray] = None
    write: bool = True


@dataclass
class Lane:
    """Group pairs run one after the other while others run at once (on a cluster whose
    workers read and write): their timings, and ``stop``, set when another lane failed."""

    stop: threading.Event
    timings: Dict[str, float] = field(default_factory=dict)


@dataclass
class PassState:
    """What a pass carries from one chunk to the next: the sums so far with the tracker
    (its state and statistics, ``result.tracker``) and CWU's count of the target phase."""

    result: PassResult
    tgt_carry: Carry
    #: seconds of the chunk tasks on the workers, carried to the client with the state
    timings: Dict[str, float] = field(default_factory=lambda: {"read": 0.0, "transfer": 0.0})


class GroupPipeline:
    """The passes over one group pair's chunks, written through ``tx``.

    ``on_worker``: the pipeline of one chunk task on a dask worker
    (hitops/calibrate/worker_chunks.py): the batches run in the task's own thread, the
    timings go to a dict of its own, and nothing is logged."""

    def __init__(self, run: RunPlan, group: GroupPlan, tx: OutputTransaction, client,
                 on_worker: bool = False, lane: Optional["Lane"] = None):
        import dask.threaded

        self.run, self.group, self.tx, self.client = run, group, tx, client
        self.on_worker = on_worker
        #: the group pairs run at once on a cluster (hitops/calibrate/passes.py): this
        #: pipeline's own timings and the signal to stop when another pair failed
        self.lane = lane
        # --scheduler sends the transfer tasks to the cluster; the tables are read and
        # written here, on this process's threads: a graph holding dask-ms table handles
        # would be unpickled by the cluster's scheduler, whose copies keep the table open
        # (and read-locked) after the run, so that the next run's commit waits on them
        self.io_scheduler = dask.threaded.get
        self.codes = [fpt.METHOD_CODES[m] for m in run.methods]
        n_workers = (len(client.scheduler_info()["workers"]) if client is not None
                     else 0 if on_worker else (os.cpu_count() or 1))
        self.tasks = BatchTasks(client, n_workers)
        self.baseline_batches = plan_groups(group.match.n_bl, max(1, 2 * n_workers))
        self.timings = {} if on_worker else run.timings if lane is None else lane.timings
        for key in ("read", "transfer", "write"):   # summed over the run's group pairs
            self.timings.setdefault(key, 0.0)
        self._cache: Dict[int, ChunkData] = {}
        # what to read: the tracker's context does not depend on its state (and on a
        # worker, the plan parts and records a packed tracker is unpacked onto)
        self.plan_tracker = self.new_tracker()
        # empty still: the first pass starts from it, so that a tracker's whole-track
        # records (the antenna tracker's: 91 MB at 10^7 rows) are not held twice
        self._plan_tracker_unused = True
        if on_worker:
            return
        if self.workers_do_io:
            log.info("%d chunk(s) of <= %d target rows, each read, tracked, transferred and "
                     "written by the workers of %s", group.n_chunks, run.chunk_rows,
                     run.opts.run.scheduler)
            return
        log.info("%d chunk(s) of <= %d target rows; %d baseline batches; scheduler %s",
                 group.n_chunks, run.chunk_rows, len(self.baseline_batches),
                 run.opts.run.scheduler or "threads")

    @property
    def workers_do_io(self) -> bool:
        """Both bands are processing sets and a cluster runs: each worker then reads and
        writes its own chunks (hitops/calibrate/worker_chunks.py)."""
        return self.client is not None and self.group.reads_stores

    @property
    def segmented(self) -> bool:
        """The tracker's counts come in segments (the n0 step per segment)."""
        return self.plan_tracker.segmented

    # ---- the stages
    def new_tracker(self) -> WrapTracker:
        """A fresh tracker of --tracker (empty state)."""
        group = self.group
        return new_tracker(self.run.opts.tracking.tracker, group.grid, group.match.corr_names,
                           group.tracking, len(group.antenna_names), list(group.antenna_names),
                           workers=1 if self.client is not None or self.on_worker else 0)

    def cached(self, k: int) -> Optional[ChunkData]:
        """Chunk ``k`` as a first pass kept it (a one-chunk run), or None."""
        return self._cache.get(k)

    def read(self, k: int, keep: bool = False) -> ChunkData:
        """Chunk ``k``, read (``keep``: cached for a second pass over a one-chunk run)."""
        if k in self._cache:
            return self._cache[k]
        stage = time.perf_counter()
        t0, t1 = self.group.bounds[k], self.group.bounds[k + 1]
        chunk = read_chunk(self.run, self.group, k, self.plan_tracker.extended(t0, t1),
                           self.plan_tracker.grids_reference, self.io_scheduler)
        if keep:
            self._cache[k] = chunk
        self.timings["read"] += time.perf_counter() - stage
        return chunk

    def close(self) -> None:
        """Stop the transfer threads."""
        self.tasks.close()

    def start_transfer(self, chunk: ChunkData, tracked: ChunkTracking,
                       offsets: Optional[np.ndarray], tgt_carry: Carry, sum_in_groups: bool,
                       offset_k: Optional[np.ndarray] = None) -> "StartedTransfer":
        """The chunk's baseline-group tasks, started (:class:`BatchTasks`)."""
        match, group = self.group.match, self.group
        scans = group.grid.scans
        scan_local = scans.scan_of_time[chunk.t0:chunk.t1]
        # per-segment sums: a segmented tracker's first pass (no per-scan shifts) with a step
        sum_segments = (tracked.segment_keys is not None and offsets is None
                        and bool(self.run.columns.offset))
        placed, group_inputs = [], []
        for bls in self.baseline_batches:
            rows, picked = batch_rows(bls, chunk.tgt_grid, chunk.ref_grid, chunk.tgt_vis,
                                      chunk.tgt_ok, chunk.ref_vis, chunk.ref_ok,
                                      chunk.ref_swapped,
                                      chunk.off_vis if sum_in_groups else None,
                                      chunk.off_ok if sum_in_groups else None,
                                      local=self.client is not None)
            inputs = TransferInputs(
                rows=rows, corr_map=match.corr_map, scan_of_time=scan_local,
                n_scan=scans.n_scan, methods=self.codes, ratio=group.ratio, eps=group.eps,
                reference=tracked.for_batch(bls), tgt_carry=tgt_carry.subset(bls),
                offsets=None if offsets is None else offsets[bls],
                offset_k=None if offset_k is None else offset_k[bls],
                nu_ref=None if group.channels is None else group.channels.ref_freq,
                segment_keys=tracked.segment_keys[bls] if sum_segments else None)
            placed.append(PlacedGroup(bls, picked, None if picked is None else rows.tgt_rows))
            group_inputs.append(inputs)
        return StartedTransfer(placed, self.tasks.start(group_inputs))

    def finish_transfer(self, chunk: ChunkData, started: "StartedTransfer"):
        """Wait for the chunk's groups: (RowOutputs, [(placed group, result)])."""
        results = self.tasks.results(started.groups)
        placed = started.placed
        out = rows_of_batches(chunk.tgt_grid, chunk.tgt_rows.size, self.group.n_corr,
                             self.codes, placed, results)
        return out, list(zip(placed, results))

    def write(self, chunk: ChunkData, out: RowOutputs) -> None:
        """Stage one chunk: each method's output and the new flags (FLAG | FLAG_ROW | not
        calibrated); the input flags are FLAG unless --overwrite read the backup of them."""
        stage = time.perf_counter()
        names = {v: k for k, v in fpt.METHOD_CODES.items()}
        new_flag = chunk.tgt_flag | chunk.tgt_flag_row[:, None, None] | ~out.calibrated[:, None, :]
        channels, delays = self.group.channels, out.delay_rows
        self.tx.write_chunk(chunk.tgt_rows, chunk.tgt_data,
                            {names[c]: out.phasor_rows[c] for c in self.codes}, new_flag,
                            self.io_scheduler, delays=None if delays is None else
                            {names[c]: delays[c] for c in self.codes},
                            chan_offset=None if channels is None else channels.chan_offset,
                            flag_read=chunk.tgt_flag if self.run.columns.flag == "FLAG" else None)
        self.timings["write"] += time.perf_counter() - stage

    # ---- the passes
    def run_pass(self, spec: PassSpec = PassSpec(), kept: Optional[Dict[int, KeptChunk]] = None,
                 keep_reads: bool = False) -> PassResult:
        """One pass over the chunks (``spec``); ``kept``: a dict that collects the output
        instead of writing (a first pass whose writing pass only shifts)."""
        state = self.start_state()
        progress = self.progress(spec)
        # the tracker reads the chunk, or zarr's reads (unlike a getcol) hold the GIL briefly
        early = state.result.tracker.grids_reference or self.group.reads_stores
        with ChunkIO(lambda k: self.read(k, keep_reads), self.group.n_chunks,
                     writes_apart=self.tx.writes_apart) as io:
            for k in range(self.group.n_chunks):
                chunk = io.chunk(k)
                if early:   # the next chunk read beside this one's tracking
                    io.read_ahead(k + 1)
                # asked for once the kernels run: casacore's getcol holds the GIL, which
                # each kernel needs to start
                out = self.advance(chunk, state, spec, kept,
                                   transfer_started=lambda: io.read_ahead(k + 1))
                if spec.write:   # on the I/O thread, after the next chunk's read
                    io.write(self.write, chunk, out)
                del chunk, out
                if progress is not None:
                    progress.update()
        return state.result

    def progress(self, spec: PassSpec) -> Optional[Progress]:
        """The pass's progress in the log (at most every 5 s; none for a one-chunk group)."""
        if self.group.n_chunks < 2:
            return None
        what = "writing pass" if spec.write else "first pass (n0 step)"
        label = f"{self.group.label} {what}" if self.group.label else what
        return Progress(f"calibrate {label}: chunks", self.group.n_chunks, logger=log)

    def start_state(self) -> PassState:
        """The state a pass starts from: a fresh tracker (the plan's, for the first pass:
        what it plans does not depend on its state), nothing carried, nothing summed."""
        tracker = self.plan_tracker if self._plan_tracker_unused else self.new_tracker()
        self._plan_tracker_unused = False
        return PassState(PassResult(samples=SampleCounts(), tracker=tracker,
                                    sums=OffsetSums.for_batch(self.group)),
                         Carry.empty(self.group.match.n_bl, self.group.n_corr))

    def advance(self, chunk: ChunkData, state: PassState, spec: PassSpec,
                kept: Optional[Dict[int, KeptChunk]] = None,
                transfer_started=None) -> RowOutputs:
        """Track and transfer one chunk, carrying ``state`` on to the next; the chunk's
        outputs in its target rows' order.  ``transfer_started``: called once the
        baseline batches run (the loop asks for the next read there)."""
        tracker, tgt_carry, result = state.result.tracker, state.tgt_carry, state.result
        stage = time.perf_counter()
        tracked = tracker.track_chunk(chunk.t0, chunk.t1, chunk.reference)
        tracked = tracked.with_segment_offsets(spec.segment_k)
        # a kept first pass sums the offsets here, from the rows (the groups then
        # need neither the target phases nor the reference/model column)
        sum_in_groups = spec.offsets is None and kept is None
        started = self.start_transfer(chunk, tracked, spec.offsets, tgt_carry, sum_in_groups,
                                      spec.offset_k)
        if transfer_started is not None:
            transfer_started()
        out, parts = self.finish_transfer(chunk, started)
        _add_parts(result, tracker, tgt_carry, parts)
        off_col = self.run.columns.offset
        if result.sums.window is not None and spec.offsets is None and off_col:
            channel_sums(result.sums, self.group, chunk, tracked.segment_keys, out)
        tracker.finish_chunk(chunk.t1)
        tgt_carry.last_scan = int(self.group.grid.scans.scan_of_time[chunk.t1 - 1])
        if kept is not None:
            kept[chunk_index(self.group, chunk)] = KeptChunk(out, tracked.segment_keys)
            if spec.offsets is None and off_col:
                self._sum_kept(result, chunk, tracked.segment_keys, out.phasor_rows,
                               out.calibrated)
        self.timings["transfer"] += time.perf_counter() - stage
        return out

    def _sum_kept(self, result: PassResult, chunk: ChunkData, seg_keys, phasor_rows,
                  calibrated) -> None:
        method = fpt.PWC if fpt.PWC in self.codes else fpt.CWU
        _add_segment_sums(result.sums, segment_row_sums(
            chunk.tgt_grid, seg_keys, chunk.tgt_vis, phasor_rows[method], calibrated,
            chunk.off_vis, chunk.off_ok), baselines=None)

def _add_parts(result: PassResult, tracker: WrapTracker, tgt_carry: Carry, parts) -> None:
    """Add the baseline batches' sample counts and offset sums; hand the tracker what its
    shares carried, and move CWU's target carry on."""
    for where, res in parts:
        bls = where.bls
        result.samples.add(res.samples)
        if res.scan_sums is not None:
            result.sums.scan_sums[bls] += res.scan_sums
            result.sums.scan_counts[bls] += res.scan_counts
        if res.segment_sums is not None:
            _add_segment_sums(result.sums, res.segment_sums, baselines=bls)
        tracker.absorb(bls, res.ref_carry, res.wrap_events)
        tgt_carry.last_phase[bls] = res.tgt_carry.last_phase
        tgt_carry.has_last[bls] = res.tgt_carry.has_last
        tgt_carry.count[bls] = res.tgt_carry.count


def _add_segment_sums(result: OffsetSums, sums: SegmentSums, baselines) -> None:
    """Add per-segment sums; ``baselines``: the run's baseline of each group-local index
    (None: the sums already use the run's baselines)."""
    for (b, c, key), z, n in zip(*sums):
        b = int(b) if baselines is None else int(baselines[b])
        entry = result.segment_sums.setdefault((b, int(c), int(key)), [0j, 0])
        entry[0] += z
        entry[1] += int(n)


def chunk_index(group: GroupPlan, chunk: ChunkData) -> int:
    """The plan's index of ``chunk`` (its first time is one of the plan's bounds)."""
    return group.bounds.index(chunk.t0)
