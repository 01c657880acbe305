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
from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from ..kernels import fpt
from ..tracking.base import WrapTracker
from .n0.step import OffsetSolution, offset_step_needed, solve_offsets
from .output import OutputTransaction
from .pipeline import GroupPipeline, KeptChunk, PassResult, PassSpec
from .plan import GroupPlan, RunPlan
from .transfer import SampleCounts
from .worker_chunks import run_pass_on_workers

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
        pipeline.write_kept(kept, solution.segment_k)
        return GroupResult.of(first, solution, group.n_chunks)
    final = _run_pass(pipeline, PassSpec(offsets=solution.offsets, segment_k=solution.segment_k,
                                         offset_k=solution.offset_k))
    return GroupResult.of(final, solution, group.n_chunks)


