"""Stages 3-5 of ``hitops calibrate`` for one group pair: read -> track -> transfer -> write.

For each time chunk of the plan, in time order:

1. read both bands (:func:`hitops.calibrate.chunk_read.read_chunk`);
2. track the reference wraps: the smooth and antenna trackers
   (:mod:`hitops.tracking`) run here on the whole chunk with their context and
   carry their state to the next chunk; the count tracker runs inside each
   baseline group's task and carries a :class:`hitops.tracking.count.Carry`;
3. transfer: :func:`hitops.calibrate.transfer.transfer_group` on baseline
   groups as dask tasks (the numba kernels of :mod:`hitops.kernels.fpt`);
4. write the outputs and new flags through the run's
   :class:`hitops.calibrate.output.OutputTransaction`.

With the n0 offset step a first pass (steps 1-3) sums the calibrated phase
against the offset reference per scan or segment; the integers are solved
(:mod:`hitops.calibrate.n0.step`) and the writing pass follows.  With a
robust tracker the first pass keeps its output when it fits in a fifth of the
memory budget, and the writing pass only shifts it by 2 pi eps k per segment
(:func:`hitops.calibrate.n0.step.offset_shifted_rows`) instead of tracking and
transferring again.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from ..tracking.count import Carry
from ..tracking.factory import new_tracker
from ..tracking.state import apply_segment_offsets
from .chunk_read import ChunkData, read_chunk, read_target
from .n0.step import OffsetSolution, offset_shifted_rows, solve_offsets
from .transfer import group_inputs, plan_groups, transfer_group

log = logging.getLogger("hitops.calibrate")

#: the causes of an uncalibrated target sample (disjoint; they add up to the flagged ones)
TOTAL_KEYS = ("n_samples", "target_invalid", "no_reference_row", "reference_invalid",
              "other_uncalibrated")


@dataclass
class PassResult:
    """What one pass over the chunks adds up."""

    totals: Dict[str, int]
    wrap_events: np.ndarray                     # (n_bl, n_corr)
    scan_sums: Optional[np.ndarray] = None      # (n_bl, n_corr, n_scan) count: per scan
    scan_counts: Optional[np.ndarray] = None
    segment_sums: Dict[tuple, list] = field(default_factory=dict)   # robust: per segment
    tracker: object = None                      # the pass's WrapTracker (None for count)


@dataclass
class GroupResult:
    """What the report of one group pair needs."""

    totals: Dict[str, int]
    wrap_events: np.ndarray
    offsets: OffsetSolution
    tracker: object
    n_chunks: int


@dataclass
class KeptChunk:
    """The first pass's output of one chunk, kept for the writing pass."""

    phasor_rows: Dict[int, np.ndarray]
    calibrated: np.ndarray
    segment_keys: Optional[np.ndarray]


class GroupPipeline:
    """The passes over one group pair's chunks, written through ``tx``."""

    def __init__(self, run, group, tx, client):
        import dask.threaded

        self.run, self.group, self.tx, self.client = run, group, tx, client
        # --scheduler sends the transfer tasks to the cluster; the tables are read and
        # written here, on this process's threads: a graph holding dask-ms table handles
        # would be unpickled by the cluster's scheduler, whose copies keep the table open
        # (and read-locked) after the run, so that the next run's commit waits on them
        self.scheduler = client.get if client is not None else dask.threaded.get
        self.io_scheduler = dask.threaded.get
        self.codes = [fpt.METHOD_CODES[m] for m in run.methods]
        n_workers = (len(client.scheduler_info()["workers"]) if client is not None
                     else (os.cpu_count() or 1))
        self.baseline_groups = plan_groups(group.match.n_bl, 2 * n_workers)
        self.timings = run.timings
        for key in ("read", "transfer", "write"):
            self.timings[key] = 0.0
        self._cache: Dict[int, ChunkData] = {}
        # extents: the tracker's context does not depend on its state
        self._extent_tracker = self.new_tracker()
        log.info("%d chunk(s) of <= %d target rows; %d baseline groups; scheduler %s",
                 group.n_chunks, run.chunk_rows, len(self.baseline_groups),
                 run.opts.scheduler or "threads")

    # ---- the stages
    def new_tracker(self):
        """A fresh smooth/antenna tracker (None for count: it runs inside the tasks)."""
        setup, group = self.group.tracking, self.group
        if setup is None:
            return None
        return new_tracker(setup.tracker, group.match, group.match.corr_names, setup,
                           len(group.antenna_names), list(group.antenna_names),
                           workers=1 if self.client is not None else 0,
                           sin_elevation=setup.sin_elevation)

    def read(self, k: int, keep: bool = False) -> ChunkData:
        """Chunk ``k``, read (``keep``: cached for a second pass over a one-chunk run)."""
        if k in self._cache:
            return self._cache[k]
        stage = time.perf_counter()
        t0, t1 = self.group.bounds[k], self.group.bounds[k + 1]
        tracker = self._extent_tracker
        extent = tracker.extended(t0, t1) if tracker is not None else (t0, t1)
        chunk = read_chunk(self.run, self.group, k, extent, self.io_scheduler)
        if keep:
            self._cache[k] = chunk
        self.timings["read"] += time.perf_counter() - stage
        return chunk

    def chunks(self, keep: bool):
        """(k, chunk k, the read of chunk k+1 or None), in time order.

        Chunk k+1 is read in a background thread while chunk k is tracked and
        transferred (casacore and the nogil numba kernels release the GIL); the
        memory budget counts that second chunk's columns (hitops/calibrate/memory.py).
        """
        from concurrent.futures import ThreadPoolExecutor

        n_chunks = self.group.n_chunks
        if n_chunks == 1:
            yield 0, self.read(0, keep), None
            return
        with ThreadPoolExecutor(1, thread_name_prefix="hitops-read") as pool:
            pending = pool.submit(self.read, 0, keep)
            for k in range(n_chunks):
                chunk = pending.result()
                pending = pool.submit(self.read, k + 1, keep) if k + 1 < n_chunks else None
                yield k, chunk, pending

    def transfer(self, chunk: ChunkData, tracked, offsets, segment_k, carries, sum_in_groups):
        """The chunk's baseline groups as dask tasks; (phasor_rows, calibrated, task results)."""
        import dask

        match, group = self.group.match, self.group
        scan_local = match.scan_of_time[chunk.t0:chunk.t1]
        ref_wraps, ref_exclude, seg_keys, ref_model = tracked
        off_col = self.run.columns.offset
        tasks = []
        for bls in self.baseline_groups:
            gi = group_inputs(bls, chunk.tgt_grid, chunk.ref_grid, chunk.tgt_vis, chunk.tgt_ok,
                              chunk.ref_vis, chunk.ref_ok, chunk.ref_swapped,
                              chunk.off_vis if sum_in_groups else None,
                              chunk.off_ok if sum_in_groups else None,
                              local=self.client is not None)
            picked = gi.pop("tgt_picked")
            local_grid = gi["tgt_rows"]
            if picked is None:   # shared chunk arrays: the grid holds chunk row indices
                local_grid, picked = None, gi["tgt_rows"]
            gi.update(corr_map=match.corr_map, scan_of_time=scan_local, n_scan=match.scans.size,
                      methods=self.codes, ratio=group.ratio, eps=group.eps,
                      ref_wraps=None if ref_wraps is None else ref_wraps[bls],
                      ref_model=None if ref_model is None else ref_model[bls],
                      ref_exclude=None if ref_exclude is None else ref_exclude[bls],
                      segment_keys=(seg_keys[bls] if seg_keys is not None and offsets is None
                                    and off_col else None),
                      ref_carry=carries[0].subset(bls), tgt_carry=carries[1].subset(bls),
                      offsets=None if offsets is None else offsets[bls])
            tasks.append((bls, picked, local_grid, dask.delayed(transfer_group, pure=False)(gi)))
        results = dask.compute(*[t[3] for t in tasks], scheduler=self.scheduler)
        placed = [t[:3] for t in tasks]   # drop the group inputs as soon as possible
        del tasks
        phasor_rows, calibrated = self._to_rows(chunk, placed, results)
        return phasor_rows, calibrated, list(zip(placed, results))

    def _to_rows(self, chunk: ChunkData, placed, results):
        """Each method's phasors and the calibrated mask in the chunk's row order."""
        n_rows, n_corr = chunk.tgt_rows.size, self.group.n_corr
        if placed[0][2] is None:
            # threads: the groups are consecutive baselines whose cells hold chunk rows, so
            # their grids stacked are the chunk's grid (one numba pass to row order)
            phasor_rows = {c: fpt.scatter_rows(
                chunk.tgt_grid, np.concatenate([r["phasors"][c] for r in results]),
                n_rows, np.complex64(0)) for c in self.codes}
            calibrated = fpt.scatter_rows(
                chunk.tgt_grid, np.concatenate([r["calibrated"] for r in results]),
                n_rows, False)
            return phasor_rows, calibrated
        # remote workers: each group's cells hold its own compact rows
        phasor_rows = {c: np.zeros((n_rows, n_corr), np.complex64) for c in self.codes}
        calibrated = np.zeros((n_rows, n_corr), dtype=bool)
        for (bls, picked, local_grid), res in zip(placed, results):
            for c in self.codes:
                phasor_rows[c][picked] = fpt.scatter_rows(local_grid, res["phasors"][c],
                                                          picked.size, np.complex64(0))
            calibrated[picked] = fpt.scatter_rows(local_grid, res["calibrated"], picked.size,
                                                  False)
        return phasor_rows, calibrated

    def write(self, chunk: ChunkData, phasor_rows, calibrated) -> None:
        """Stage one chunk: each method's output and the new flags (FLAG | FLAG_ROW | not calibrated)."""
        stage = time.perf_counter()
        names = {v: k for k, v in fpt.METHOD_CODES.items()}
        new_flag = chunk.tgt_flag | chunk.tgt_flag_row[:, None, None] | ~calibrated[:, None, :]
        self.tx.write_chunk(chunk.tgt_rows, chunk.tgt_data,
                            {names[c]: phasor_rows[c] for c in self.codes}, new_flag,
                            self.io_scheduler)
        self.timings["write"] += time.perf_counter() - stage

    # ---- the passes
    def run_pass(self, offsets=None, segment_k=None, write=True, kept=None,
                 keep_reads=False) -> PassResult:
        """One pass over the chunks.  ``offsets``: per-scan n0 shifts (count); ``segment_k``:
        per-segment integers (robust trackers); ``kept``: a dict that collects the output
        instead of writing (a first pass whose writing pass only shifts)."""
        match, n_corr, n_scan = self.group.match, self.group.n_corr, self.group.match.scans.size
        off_col = self.run.columns.offset
        tracker = self.new_tracker()
        carries = (Carry.empty(match.n_bl, n_corr), Carry.empty(match.n_bl, n_corr))
        result = PassResult(totals={k: 0 for k in TOTAL_KEYS},
                            wrap_events=np.zeros((match.n_bl, n_corr), dtype=np.int64),
                            scan_sums=np.zeros((match.n_bl, n_corr, n_scan), dtype=np.complex128),
                            scan_counts=np.zeros((match.n_bl, n_corr, n_scan), dtype=np.int64),
                            tracker=tracker)
        for k, chunk, next_read in self.chunks(keep_reads):
            stage = time.perf_counter()
            tracked = (None, None, None, None)
            if tracker is not None:
                t_lo, t_hi, ext_vis, ext_valid, ext_sigma = chunk.ext
                wraps, exclude, keys, model = tracker.track(
                    t_lo, chunk.t0, chunk.t1, t_hi, ext_vis, ext_valid, ext_sigma).as_tuple()
                tracked = (apply_segment_offsets(wraps, keys, segment_k), exclude, keys, model)
            # a kept first pass sums the offsets here, from the rows (the groups then need
            # neither the target phases nor the reference/model column)
            sum_in_groups = offsets is None and kept is None
            phasor_rows, calibrated, parts = self.transfer(chunk, tracked, offsets, segment_k,
                                                           carries, sum_in_groups)
            _add_parts(result, carries, parts)
            last_scan = int(match.scan_of_time[chunk.t1 - 1])
            carries[0].last_scan = carries[1].last_scan = last_scan
            if kept is not None:
                kept[k] = KeptChunk(phasor_rows, calibrated, tracked[2])
                if offsets is None and off_col:
                    self._sum_kept(result, chunk, tracked[2], phasor_rows, calibrated)
            self.timings["transfer"] += time.perf_counter() - stage
            if next_read is not None:
                # the next chunk's read ends before this chunk's write starts: the two never
                # touch the target table at the same time
                next_read.result()
            if write:
                self.write(chunk, phasor_rows, calibrated)
        if tracker is not None:
            result.wrap_events = tracker.stats.per_series["wrap_events"].copy()
            result.totals["jump_flagged"] = int(tracker.stats.per_series["jump_flagged"].sum())
        return result

    def _sum_kept(self, result: PassResult, chunk: ChunkData, seg_keys, phasor_rows,
                  calibrated) -> None:
        from ..kernels.segments import segment_row_sums

        method = fpt.PWC if fpt.PWC in self.codes else fpt.CWU
        for (b, c, key), z, n in zip(*segment_row_sums(
                chunk.tgt_grid, seg_keys, chunk.tgt_vis, phasor_rows[method], calibrated,
                chunk.off_vis, chunk.off_ok)):
            entry = result.segment_sums.setdefault((int(b), int(c), int(key)), [0j, 0])
            entry[0] += z
            entry[1] += int(n)

    def write_kept(self, kept: Dict[int, KeptChunk], segment_k) -> None:
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
                    [part.phasor_rows[c] for c in shifted])):
                part.phasor_rows[c] = out
            self.timings["offset_apply"] = (self.timings.get("offset_apply", 0.0)
                                            + time.perf_counter() - stage)
            self.write(chunk, part.phasor_rows, part.calibrated)


def _add_parts(result: PassResult, carries, parts) -> None:
    """Add the baseline groups' totals, wrap events and offset sums; move the carries on."""
    for (bls, _, _), res in parts:
        for key in TOTAL_KEYS:
            result.totals[key] += res[key]
        result.wrap_events[bls] += res["wrap_events"]
        if "offset_sums" in res:
            result.scan_sums[bls] += res["offset_sums"]
            result.scan_counts[bls] += res["offset_counts"]
        if "segment_sums" in res:
            for (lb, c, key), z, n in zip(*res["segment_sums"]):
                entry = result.segment_sums.setdefault((int(bls[lb]), int(c), int(key)), [0j, 0])
                entry[0] += z
                entry[1] += int(n)
        for carry, part in zip(carries, (res["ref_carry"], res["tgt_carry"])):
            carry.last_phase[bls] = part.last_phase
            carry.has_last[bls] = part.has_last
            carry.count[bls] = part.count


def kept_bytes(group, n_methods: int) -> int:
    """Memory the first pass's kept output takes: phasors, mask and segment keys."""
    n_time, n_bl = group.match.n_time, group.match.n_bl
    return group.n_target_rows * group.n_corr * (8 * n_methods + 1) + n_bl * group.n_corr * n_time * 8


def run_group(run, group, tx, client) -> GroupResult:
    """Every pass over one group pair; the outputs staged in ``tx``."""
    pipeline = GroupPipeline(run, group, tx, client)
    codes, columns = pipeline.codes, run.columns
    step = bool(columns.offset) and (fpt.PWC in codes or fpt.CWU in codes)
    if columns.offset and not step:
        log.warning("%s applies to pwc and cwu only; ignored for cfpt",
                    "--offset-model" if columns.offset_is_model else "--offset-reference-column")
    elif step and group.eps == 0.0:
        log.info("integer R: PWC has no n0 offset; the offset step is skipped")
        step = False
    if not step:
        final = pipeline.run_pass()
        return GroupResult(final.totals, final.wrap_events, OffsetSolution(), final.tracker,
                           group.n_chunks)
    # with a robust tracker the first pass's output is kept when it fits (a fifth of the
    # budget), and the writing pass shifts it; otherwise the writing pass runs again
    keep = group.tracking is not None and kept_bytes(group, len(codes)) <= run.budget // 5
    kept = {} if keep else None
    first = pipeline.run_pass(write=False, kept=kept, keep_reads=group.n_chunks == 1)
    solution = solve_offsets(run, group, first)
    if keep:
        pipeline.write_kept(kept, solution.segment_k)
        return GroupResult(first.totals, first.wrap_events, solution, first.tracker,
                           group.n_chunks)
    final = pipeline.run_pass(offsets=solution.offsets, segment_k=solution.segment_k)
    return GroupResult(final.totals, final.wrap_events, solution, final.tracker, group.n_chunks)
