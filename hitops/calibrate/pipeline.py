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
k+1's run.

With the n0 offset step a first pass (steps 1-3) sums the calibrated phase against the offset
reference per scan or segment (per target channel across a window); the integers are solved
(:mod:`hitops.calibrate.n0.step`) and the writing pass follows.  With a segmented tracker (smooth,
antenna) the first pass keeps its output when it fits in a fifth of the memory budget, and the
writing pass only shifts it by 2 pi eps k per segment
(:func:`hitops.calibrate.n0.step.offset_shifted_rows`) instead of tracking and transferring again.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from ..kernels.segments import SegmentSums, segment_row_sums
from ..tracking.base import ChunkTracking, WrapTracker
from ..tracking.count import Carry
from ..tracking.factory import new_tracker
from .chunk_io import ChunkIO
from .chunk_read import ChunkData, read_chunk, read_target
from .batch_tasks import BatchTasks, StartedGroups
from .n0.step import (OffsetSolution, OffsetSums, channel_sums, offset_shifted_rows,
                      offset_step_needed, solve_offsets)
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
class GroupResult:
    """What the report of one group pair needs."""

    samples: SampleCounts
    jump_flagged: int
    wrap_events: np.ndarray                     # (n_bl, n_corr)
    offsets: OffsetSolution
    tracker: WrapTracker
    n_chunks: int

    @classmethod
    def of(cls, result: PassResult, offsets: OffsetSolution, n_chunks: int) -> "GroupResult":
        return cls(result.samples, result.jump_flagged, result.wrap_events, offsets,
                   result.tracker, n_chunks)


@dataclass
class KeptChunk:
    """The first pass's output of one chunk, kept for the writing pass."""

    outputs: RowOutputs
    segment_keys: Optional[np.ndarray]


@dataclass
class StartedTransfer:
    """A chunk's baseline-group tasks, started, and where each group's output goes."""

    placed: List[PlacedGroup]
    groups: StartedGroups


class GroupPipeline:
    """The passes over one group pair's chunks, written through ``tx``."""

    def __init__(self, run: RunPlan, group: GroupPlan, tx: OutputTransaction, client):
        import dask.threaded

        self.run, self.group, self.tx, self.client = run, group, tx, client
        # --scheduler sends the transfer tasks to the cluster; the tables are read and
        # written here, on this process's threads: a graph holding dask-ms table handles
        # would be unpickled by the cluster's scheduler, whose copies keep the table open
        # (and read-locked) after the run, so that the next run's commit waits on them
        self.io_scheduler = dask.threaded.get
        self.codes = [fpt.METHOD_CODES[m] for m in run.methods]
        n_workers = (len(client.scheduler_info()["workers"]) if client is not None
                     else (os.cpu_count() or 1))
        self.tasks = BatchTasks(client, n_workers)
        self.baseline_batches = plan_groups(group.match.n_bl, 2 * n_workers)
        self.timings = run.timings
        for key in ("read", "transfer", "write"):
            self.timings[key] = 0.0
        self._cache: Dict[int, ChunkData] = {}
        # what to read: the tracker's context does not depend on its state
        self._reader = self.new_tracker()
        log.info("%d chunk(s) of <= %d target rows; %d baseline batches; scheduler %s",
                 group.n_chunks, run.chunk_rows, len(self.baseline_batches),
                 run.opts.run.scheduler or "threads")

    @property
    def segmented(self) -> bool:
        """The tracker's counts come in segments (the n0 step per segment)."""
        return self._reader.segmented

    # ---- the stages
    def new_tracker(self) -> WrapTracker:
        """A fresh tracker of --tracker (empty state)."""
        group = self.group
        return new_tracker(self.run.opts.tracking.tracker, group.grid, group.match.corr_names,
                           group.tracking, len(group.antenna_names), list(group.antenna_names),
                           workers=1 if self.client is not None else 0)

    def read(self, k: int, keep: bool = False) -> ChunkData:
        """Chunk ``k``, read (``keep``: cached for a second pass over a one-chunk run)."""
        if k in self._cache:
            return self._cache[k]
        stage = time.perf_counter()
        t0, t1 = self.group.bounds[k], self.group.bounds[k + 1]
        chunk = read_chunk(self.run, self.group, k, self._reader.extended(t0, t1),
                           self._reader.grids_reference, self.io_scheduler)
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
    def run_pass(self, offsets: Optional[np.ndarray] = None,
                 segment_k: Optional[Dict[tuple, int]] = None, write: bool = True,
                 kept: Optional[Dict[int, KeptChunk]] = None,
                 keep_reads: bool = False, offset_k: Optional[np.ndarray] = None) -> PassResult:
        """One pass over the chunks.  ``offsets``: per-scan n0 shifts (count) and ``offset_k``
        their integers (a per-channel transfer's delays need them); ``segment_k``:
        per-segment integers (segmented trackers); ``kept``: a dict that collects the output
        instead of writing (a first pass whose writing pass only shifts)."""
        match, n_corr, scans = self.group.match, self.group.n_corr, self.group.grid.scans
        off_col = self.run.columns.offset
        tracker = self.new_tracker()
        tgt_carry = Carry.empty(match.n_bl, n_corr)
        result = PassResult(samples=SampleCounts(), tracker=tracker,
                            sums=OffsetSums.for_batch(self.group))
        with ChunkIO(lambda k: self.read(k, keep_reads), self.group.n_chunks) as io:
            for k in range(self.group.n_chunks):
                chunk = io.chunk(k)
                if tracker.grids_reference:   # the tracker reads the chunk here: read beside it
                    io.read_ahead(k + 1)
                stage = time.perf_counter()
                tracked = tracker.track_chunk(chunk.t0, chunk.t1, chunk.reference)
                tracked = tracked.with_segment_offsets(segment_k)
                # a kept first pass sums the offsets here, from the rows (the groups then
                # need neither the target phases nor the reference/model column)
                sum_in_groups = offsets is None and kept is None
                started = self.start_transfer(chunk, tracked, offsets, tgt_carry,
                                              sum_in_groups, offset_k)
                # asked for once the kernels run: casacore's getcol holds the GIL, which
                # each kernel needs to start
                io.read_ahead(k + 1)
                out, parts = self.finish_transfer(chunk, started)
                _add_parts(result, tracker, tgt_carry, parts)
                if result.sums.window is not None and offsets is None and off_col:
                    channel_sums(result.sums, self.group, chunk, tracked.segment_keys, out)
                tracker.finish_chunk(chunk.t1)
                tgt_carry.last_scan = int(scans.scan_of_time[chunk.t1 - 1])
                if kept is not None:
                    kept[k] = KeptChunk(out, tracked.segment_keys)
                    if offsets is None and off_col:
                        self._sum_kept(result, chunk, tracked.segment_keys, out.phasor_rows,
                                       out.calibrated)
                self.timings["transfer"] += time.perf_counter() - stage
                if write:   # on the I/O thread, after the next chunk's read
                    io.write(self.write, chunk, out)
                del chunk, out, parts, started, tracked
        return result

    def _sum_kept(self, result: PassResult, chunk: ChunkData, seg_keys, phasor_rows,
                  calibrated) -> None:
        method = fpt.PWC if fpt.PWC in self.codes else fpt.CWU
        _add_segment_sums(result.sums, segment_row_sums(
            chunk.tgt_grid, seg_keys, chunk.tgt_vis, phasor_rows[method], calibrated,
            chunk.off_vis, chunk.off_ok), baselines=None)

    def write_kept(self, kept: Dict[int, KeptChunk], segment_k: Dict[tuple, int]) -> None:
        """The writing pass from the first pass's kept output, shifted by the step's k."""
        for k in range(self.group.n_chunks):
            if k in self._cache:
                chunk = self._cache[k]
            else:   # the target rows only: the reference band has done its work
                stage = time.perf_counter()
                chunk = read_target(self.run, self.group, k, self.io_scheduler)
                self.timings["read"] += time.perf_counter() - stage
            part = kept.pop(k)
            stage = time.perf_counter()
            shifted = [c for c in self.codes if c in (fpt.PWC, fpt.CWU)]
            for c, out in zip(shifted, offset_shifted_rows(
                    chunk.tgt_grid, self.group.eps, segment_k, part.segment_keys,
                    [part.outputs.phasor_rows[c] for c in shifted])):
                part.outputs.phasor_rows[c] = out
            self.timings["offset_apply"] = (self.timings.get("offset_apply", 0.0)
                                            + time.perf_counter() - stage)
            self.write(chunk, part.outputs)


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


def kept_bytes(group: GroupPlan, n_methods: int) -> int:
    """Memory the first pass's kept output takes: phasors, mask and segment keys."""
    n_time, n_bl = group.match.n_time, group.match.n_bl
    return group.n_target_rows * group.n_corr * (8 * n_methods + 1) + n_bl * group.n_corr * n_time * 8


def run_group(run: RunPlan, group: GroupPlan, tx: OutputTransaction, client) -> GroupResult:
    """Every pass over one group pair; the outputs staged in ``tx``."""
    pipeline = GroupPipeline(run, group, tx, client)
    try:
        return _run_passes(run, group, pipeline)
    finally:
        pipeline.close()


def _run_passes(run: RunPlan, group: GroupPlan, pipeline: GroupPipeline) -> GroupResult:
    codes, columns = pipeline.codes, run.columns
    step = bool(columns.offset) and (fpt.PWC in codes or fpt.CWU in codes)
    if columns.offset and not step:
        log.warning("%s applies to pwc and cwu only; ignored for cfpt",
                    "--offset-model" if columns.offset_is_model else "--offset-reference-column")
    elif step and not offset_step_needed(group):
        step = False
    if not step:
        return GroupResult.of(pipeline.run_pass(), OffsetSolution(), group.n_chunks)
    # with a tracker whose n0 step is per segment the first pass's output is kept when it
    # fits (a fifth of the budget), and the writing pass shifts it; otherwise the writing
    # pass runs again
    # (not for a per-channel transfer: its delays would need the same shift)
    keep = (pipeline.segmented and group.channels is None
            and kept_bytes(group, len(codes)) <= run.budget // 5)
    kept = {} if keep else None
    first = pipeline.run_pass(write=False, kept=kept, keep_reads=group.n_chunks == 1)
    solution = solve_offsets(run, group, first.tracker, first.sums)
    if keep:
        pipeline.write_kept(kept, solution.segment_k)
        return GroupResult.of(first, solution, group.n_chunks)
    final = pipeline.run_pass(offsets=solution.offsets, segment_k=solution.segment_k,
                              offset_k=solution.offset_k)
    return GroupResult.of(final, solution, group.n_chunks)
