"""Stage 4 of ``hitops calibrate`` for one group pair: its passes, and where each runs.

Without the n0 offset step one writing pass; with it a first pass that sums, the
step's integers solved on this process (:mod:`hitops.calibrate.n0.step`), and a
writing pass (or, for a segmented tracker whose first pass's output fits, that output
shifted by 2 pi eps k per segment).  A pass runs here
(:meth:`GroupPipeline.run_pass <hitops.calibrate.pipeline.GroupPipeline.run_pass>`:
this process reads and writes, the kernels on its threads or on a cluster) or, when
both bands are processing sets and a cluster runs, as chunk tasks that read and write
on the workers (:func:`hitops.calibrate.worker_chunks.run_pass_on_workers`).
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from ..tracking.base import WrapTracker
from .n0.step import OffsetSolution, offset_step_needed, solve_offsets
from .output import OutputTransaction
from .kept import KeptChunk, write_kept
from .pipeline import GroupPipeline, Lane, PassResult, PassSpec
from .plan import GroupPlan, RunPlan
from .transfer import SampleCounts
from .worker_chunks import LaneStopped, run_pass_on_workers

log = logging.getLogger("hitops.calibrate")


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


def _run_pass(pipeline: GroupPipeline, spec: PassSpec,
              kept: Optional[Dict[int, KeptChunk]] = None,
              keep_reads: bool = False) -> PassResult:
    """One pass, on the workers when they read and write, else here."""
    if pipeline.workers_do_io:
        return run_pass_on_workers(pipeline, spec)
    return pipeline.run_pass(spec, kept=kept, keep_reads=keep_reads)


def kept_bytes(group: GroupPlan, n_methods: int) -> int:
    """Memory the first pass's kept output takes: phasors, mask and segment keys."""
    n_time, n_bl = group.match.n_time, group.match.n_bl
    return group.n_target_rows * group.n_corr * (8 * n_methods + 1) + n_bl * group.n_corr * n_time * 8


def run_groups(run: RunPlan, tx: OutputTransaction, client) -> List[GroupResult]:
    """Every group pair's passes, each pair's result in the plan's order.

    One pair after the other, except on a cluster whose workers read and write: there
    the pairs of different target partitions run at once (each a chain of chunk tasks
    whose advances follow each other; two chains at once keep twice as many workers
    busy), and the pairs of one partition one after the other (a partition holding
    several fields interleaves their time steps, so their writes may share a zarr chunk
    of the new arrays and must not run at once)."""
    if client is None or not workers_do_io(run):
        return [run_group(run, group, tx, client) for group in run.groups]
    lanes: Dict[str, List[int]] = {}
    for i, group in enumerate(run.groups):
        lanes.setdefault(group.match.datasets["tgt"].partition, []).append(i)
    if len(lanes) < 2:
        return [run_group(run, group, tx, client) for group in run.groups]
    return _run_lanes(run, tx, client, list(lanes.values()))


def _run_lanes(run: RunPlan, tx: OutputTransaction, client,
               lanes: List[List[int]]) -> List[GroupResult]:
    """The lanes' group pairs, each lane on a thread of its own; the first failure stops
    the others (at their next chunk, their tasks waited for) and is raised."""
    stop = threading.Event()
    results: Dict[int, GroupResult] = {}
    states = [Lane(stop) for _ in lanes]

    def one_lane(indices: List[int], lane: Lane) -> None:
        for i in indices:
            results[i] = run_group(run, run.groups[i], tx, client, lane)

    with ThreadPoolExecutor(len(lanes), thread_name_prefix="hitops-lane") as pool:
        futures = [pool.submit(one_lane, indices, lane) for indices, lane in zip(lanes, states)]
        try:
            wait(futures, return_when=FIRST_EXCEPTION)
        finally:   # an error, or an interrupt here: the other lanes stop at their next chunk
            if not all(f.done() and f.exception() is None for f in futures):
                stop.set()
    errors = [f.exception() for f in futures if f.exception() is not None]
    first = next((e for e in errors if not isinstance(e, LaneStopped)), None)
    if first is not None or errors:
        raise first or errors[0]
    for lane in states:
        for key, seconds in lane.timings.items():
            run.timings[key] = run.timings.get(key, 0.0) + seconds
    return [results[i] for i in range(len(run.groups))]


def workers_do_io(run: RunPlan) -> bool:
    """Every group pair of ``run`` reads processing sets in both bands (on a cluster, the
    workers then read and write each chunk: hitops/calibrate/worker_chunks.py)."""
    return all(group.reads_stores for group in run.groups)


def run_group(run: RunPlan, group: GroupPlan, tx: OutputTransaction, client,
              lane: Optional[Lane] = None) -> GroupResult:
    """Every pass over one group pair; the outputs staged in ``tx`` (``lane``: run at once
    with others, :func:`run_groups`)."""
    pipeline = GroupPipeline(run, group, tx, client, lane=lane)
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
        return GroupResult.of(_run_pass(pipeline, PassSpec()), OffsetSolution(), group.n_chunks)
    # with a tracker whose n0 step is per segment the first pass's output is kept when it
    # fits (a fifth of the budget), and the writing pass shifts it; otherwise the writing
    # pass runs again
    # (not for a per-channel transfer: its delays would need the same shift; not when the
    # workers read and write: the output stays on them)
    keep = (pipeline.segmented and group.channels is None and not pipeline.workers_do_io
            and kept_bytes(group, len(codes)) <= run.budget // 5)
    kept = {} if keep else None
    first = _run_pass(pipeline, PassSpec(write=False), kept=kept,
                      keep_reads=group.n_chunks == 1)
    solution = solve_offsets(run, group, first.tracker, first.sums)
    if keep:
        write_kept(pipeline, kept, solution.segment_k)
        return GroupResult.of(first, solution, group.n_chunks)
    # the writing pass tracks again from a fresh tracker: the first pass's (its records
    # span the whole track) need not be held beside it
    del first
    final = _run_pass(pipeline, PassSpec(offsets=solution.offsets, segment_k=solution.segment_k,
                                         offset_k=solution.offset_k))
    return GroupResult.of(final, solution, group.n_chunks)


