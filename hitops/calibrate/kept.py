"""The writing pass of a kept first pass: the n0 step's shift of output kept in memory.

With a segmented tracker (smooth, antenna) and the n0 step, the first pass keeps each
chunk's output when it fits in a fifth of the memory budget (hitops/calibrate/passes.py);
the writing pass then reads the target's rows only, moves each method's output by
2 pi eps k per segment (:func:`hitops.calibrate.n0.step.offset_shifted_rows`) and writes
it, instead of tracking and transferring again.  The target's reads and the writes run
on :class:`~hitops.calibrate.chunk_io.ChunkIO`'s threads, the shift on the calling
thread: chunk k+1 is read while chunk k is shifted, and chunk k is written while k+1 is
(at most three target chunks at once, fewer bytes than the two chunks of both bands
the first pass held).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np

from ..kernels import fpt
from .chunk_io import ChunkIO
from .chunk_read import ChunkData, read_target
from .n0.step import offset_shifted_rows
from .row_outputs import RowOutputs


@dataclass
class KeptChunk:
    """The first pass's output of one chunk, kept for the writing pass."""

    outputs: RowOutputs
    segment_keys: Optional[np.ndarray]


def write_kept(pipeline, kept: Dict[int, KeptChunk], segment_k: Dict[tuple, int]) -> None:
    """The writing pass of ``pipeline``'s group (a
    :class:`~hitops.calibrate.pipeline.GroupPipeline`, which imports this module, so the
    type is not imported here) from the first pass's ``kept`` output, shifted by the n0
    step's integers ``segment_k``; written through its transaction."""
    run, group, timings = pipeline.run, pipeline.group, pipeline.timings

    def read(k: int) -> ChunkData:
        chunk = pipeline.cached(k)
        if chunk is not None:
            return chunk
        stage = time.perf_counter()
        # the target rows only: the reference band has done its work
        chunk = read_target(run, group, k, pipeline.io_scheduler)
        timings["read"] += time.perf_counter() - stage
        return chunk

    shifted = [c for c in pipeline.codes if c in (fpt.PWC, fpt.CWU)]
    with ChunkIO(read, group.n_chunks, writes_apart=pipeline.tx.writes_apart) as io:
        for k in range(group.n_chunks):
            chunk = io.chunk(k)
            io.read_ahead(k + 1)
            part = kept.pop(k)
            stage = time.perf_counter()
            for c, out in zip(shifted, offset_shifted_rows(
                    chunk.tgt_grid, group.eps, segment_k, part.segment_keys,
                    [part.outputs.phasor_rows[c] for c in shifted])):
                part.outputs.phasor_rows[c] = out
            timings["offset_apply"] = (timings.get("offset_apply", 0.0)
                                       + time.perf_counter() - stage)
            io.write(pipeline.write, chunk, part.outputs)
            del chunk, part
