"""Stage 4 of ``hitops calibrate`` on a cluster over processing sets: each worker reads and writes its own chunks.

When both bands are MSv4 processing sets and ``--scheduler`` names a cluster, a pass
over a group pair's chunks is three tasks per chunk, all on the workers:

* ``read``: the chunk's rows of both bands, read from the zarr stores by the worker
  (:meth:`GroupPipeline.read <hitops.calibrate.pipeline.GroupPipeline.read>`; the
  stores are opened by path, so no array goes through the client);
* ``advance``: track and transfer the chunk (:meth:`GroupPipeline.advance`), from the
  state the previous chunk's ``advance`` carried out (a :class:`PassState`: the
  tracker with its state and statistics, CWU's target carry and the sums of the
  pass); chunk k+1's ``advance`` waits for chunk k's, so the wrap tracking runs in
  time order as in one process, and the next chunks' reads and the last chunks'
  writes run beside it on the other workers;
* ``write``: the chunk's outputs into their own cells of the staged data groups
  (:meth:`DataGroupTransaction.write_chunk
  <hitops.calibrate.output_msv4.DataGroupTransaction.write_chunk>`).  Chunk k's write
  waits for chunk k-1's: the staged arrays are stored in zarr chunks of about one run
  chunk's time steps, but a run chunk's bounds follow the rows of both bands and need
  not fall on a zarr chunk's edge, so two neighbouring chunks may share a zarr chunk,
  which zarr reads, changes and writes back; in order, never at once (two workers
  doing that at once would lose one's cells).

The client sends the plan once (:class:`ChunkJob`, scattered to every worker), submits
a few chunks ahead of the last finished write (:func:`in_flight`: the workers hold at
most that many chunks), and gathers only the pass's last state, each write's time and,
for the antenna tracker, the part of its whole-track records each chunk filled.
A chunk's three tasks prefer one worker (chunk k the k-th worker in turn, others
allowed), so its visibilities stay where they were read and only the small state
moves from worker to worker.
The commit (registering the groups) stays on the client, after every write has
returned.  A failure on a worker (or an interrupt here) cancels the run's tasks and
waits until none runs before the transaction rolls back, so no write lands in an
array after it was removed.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
import uuid
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Deque, Dict, List, Optional

import numpy as np

from .chunk_read import ChunkData
from .output_msv4 import DataGroupTransaction
from .pipeline import GroupPipeline, PassResult, PassSpec, PassState
from .plan import GroupPlan, RunPlan
from .row_outputs import RowOutputs

log = logging.getLogger("hitops.calibrate")

#: seconds to wait for a failed run's tasks to stop before the rollback goes on anyway
STOP_WAIT_S = 120.0
#: looks 0.1 s apart that must find none of the run's tasks on the workers
QUIET_POLLS = 4


class LaneStopped(Exception):
    """A group pair's chain stopped because another one, running at once, failed (that
    one's error is what the run raises: hitops/calibrate/passes.py)."""


@dataclass(frozen=True)
class ChunkJob:
    """What every chunk task of one pass needs, sent to each worker once."""

    run: RunPlan
    group: GroupPlan
    tx: DataGroupTransaction
    spec: PassSpec

    @cached_property
    def pipeline(self) -> GroupPipeline:
        """The worker's pipeline of this job, made by its first task (a worker holds one
        copy of the job, which every task of the pass on it receives)."""
        return GroupPipeline(self.run, self.group, self.tx, None, on_worker=True)


@dataclass(frozen=True)
class ReadChunk:
    """A chunk read on a worker, and the seconds the read took."""

    chunk: ChunkData
    seconds: float


@dataclass(frozen=True)
class Advanced:
    """A chunk tracked and transferred: the state carried on (its tracker packed:
    :meth:`~hitops.tracking.base.WrapTracker.packed`), the chunk's outputs, and what it
    filled of the tracker's whole-track records (the antenna tracker's; {} for others)."""

    state: PassState
    outputs: RowOutputs
    records: Dict[str, np.ndarray]


def in_flight(n_workers: int) -> int:
    """Chunks submitted ahead of the oldest unfinished write: enough for every worker to
    read, advance or write one, and one more, so the advance chain never waits for a read."""
    return 2 * max(1, n_workers) + 1


# ---- the tasks (run on the workers)
def read_task(job: ChunkJob, k: int) -> ReadChunk:
    """Chunk ``k`` of both bands, read from the stores by this worker."""
    start = time.perf_counter()
    chunk = job.pipeline.read(k)
    return ReadChunk(chunk, time.perf_counter() - start)


def advance_task(job: ChunkJob, read: ReadChunk, state: PassState) -> Advanced:
    """Chunk ``read`` tracked and transferred from ``state`` (a copy is carried on: the
    previous task's result may be this worker's own, held for other tasks)."""
    start = time.perf_counter()
    chunk, pipeline = read.chunk, job.pipeline
    state = copy.deepcopy(state)
    # the plan parts and record arrays of this worker's own tracker of the run (each
    # chunk fills its own times of the records, cleared first)
    tracker = state.result.tracker.unpacked(pipeline.plan_tracker)
    tracker.clear_records(chunk.t0, chunk.t1)
    state.result.tracker = tracker
    outputs = pipeline.advance(chunk, state, job.spec)
    state.result.tracker = tracker.packed()
    state.timings["read"] += read.seconds
    state.timings["transfer"] += time.perf_counter() - start
    return Advanced(state, outputs, tracker.record_slices(chunk.t0, chunk.t1))


def state_of(advanced: Advanced) -> PassState:
    """The state alone (the next chunk's advance need not fetch this one's outputs)."""
    return advanced.state


def records_of(advanced: Advanced) -> Dict[str, np.ndarray]:
    """The records a chunk filled (fetched by the client)."""
    return advanced.records


def write_task(job: ChunkJob, read: ReadChunk, advanced: Advanced, after=None) -> float:
    """Chunk ``read``'s outputs into its cells of the staged groups; the seconds it took.
    ``after``: the previous chunk's write (only waited for, see the module's docstring)."""
    start = time.perf_counter()
    job.pipeline.write(read.chunk, advanced.outputs)
    return time.perf_counter() - start


# ---- the client's side
@dataclass
class ChunkFutures:
    """One chunk's tasks, held until its last one has finished."""

    k: int
    read: object
    advance: object
    state: object
    last: object          # the write (a writing pass) or the state (a first pass)
    records: object       # what the chunk filled of the tracker's records, or None


def run_pass_on_workers(pipeline: GroupPipeline, spec: PassSpec) -> PassResult:
    """One pass over ``pipeline``'s chunks as chunk tasks on its cluster."""
    client, group = pipeline.client, pipeline.group
    token = uuid.uuid4().hex[:12]
    # the run without its other groups (a worker reads this one)
    run = dataclasses.replace(pipeline.run, groups=[group])
    job = client.scatter(ChunkJob(run, group, pipeline.tx, spec), broadcast=True, hash=False)
    start = pipeline.start_state()
    tracker = start.result.tracker      # the client's, which the records are put back into
    start.result.tracker = tracker.packed()
    state = client.scatter(start, hash=False)
    workers = sorted(client.scheduler_info()["workers"])
    window = in_flight(len(workers))
    flight: Deque[ChunkFutures] = deque()
    progress = pipeline.progress(spec)
    try:
        last = None
        for k in range(group.n_chunks):
            flight.append(_submit_chunk(client, job, (state, last), k, token, spec.write,
                                        workers[k % len(workers)], bool(tracker.records)))
            state, last = flight[-1].state, flight[-1].last
            if pipeline.lane is not None and pipeline.lane.stop.is_set():
                raise LaneStopped(f"group pair {group.label} stopped: another one failed")
            while len(flight) > (window if k + 1 < group.n_chunks else 0):
                _finish(pipeline, flight.popleft(), spec.write, tracker)
                if progress is not None:
                    progress.update()
        final: PassState = state.result()
    except BaseException:
        _stop(client, token, flight)
        raise
    for key in ("read", "transfer"):
        pipeline.timings[key] += final.timings[key]
    if spec.write:
        pipeline.tx.mark_written(group.match.datasets["tgt"])
    final.result.tracker = final.result.tracker.unpacked(tracker)
    return final.result


def _submit_chunk(client, job, before, k: int, token: str, write: bool, worker: str,
                  records: bool) -> ChunkFutures:
    """Chunk ``k``'s tasks, from the previous chunk's (state, write) ``before`` (its write
    after the previous one), on ``worker`` if it is free; the earlier chunks' go first
    (dask: higher priority first).  ``records``: fetch what it filled of them."""
    state, after = before

    def submit(step: str, fn, *args):
        return client.submit(fn, *args, key=f"hitops-{step}-{token}-{k}", priority=-k,
                             workers=[worker], allow_other_workers=True)

    read = submit("read", read_task, job, k)
    advanced = submit("advance", advance_task, job, read, state)
    carried = submit("state", state_of, advanced)
    last = submit("write", write_task, job, read, advanced, after) if write else carried
    return ChunkFutures(k, read, advanced, carried, last,
                        submit("records", records_of, advanced) if records else None)


def _finish(pipeline: GroupPipeline, chunk: ChunkFutures, write: bool, tracker) -> None:
    """Wait for a chunk's last task (its error raises here), put what it filled of the
    tracker's records into ``tracker``, and let its results go."""
    if write:
        pipeline.timings["write"] += chunk.last.result()
    else:
        chunk.last.result()
    if chunk.records is not None:
        bounds = pipeline.group.bounds
        tracker.put_records(bounds[chunk.k], bounds[chunk.k + 1], chunk.records.result())


def _stop(client, token: str, flight: Deque[ChunkFutures]) -> None:
    """Cancel the run's tasks and wait until none of them runs on a worker any more."""
    stop_tasks(client, token, [f for c in flight for f in (c.read, c.advance, c.state, c.last,
                                                           c.records) if f is not None])


def stop_tasks(client, token: str, futures: List[object]) -> None:
    """Cancel ``futures`` and wait until no task whose key holds ``token`` runs, or may
    still start, on a worker (also hitops/calibrate/table_workers.py's)."""
    try:
        client.cancel(futures, force=True)
        deadline = time.monotonic() + STOP_WAIT_S
        quiet = 0
        while time.monotonic() < deadline:
            # idle several times running: a task the scheduler sent just before the
            # cancel reaches its worker within milliseconds (its messages are batched),
            # and one look could come before it
            quiet = 0 if any(client.run(_running, token).values()) else quiet + 1
            if quiet >= QUIET_POLLS:
                return
            time.sleep(0.1)
        log.warning("tasks of this run still run on the cluster after %.0f s; removing the "
                    "staged data groups anyway", STOP_WAIT_S)
    except Exception as err:   # the run's own error matters more
        log.warning("could not confirm that the cluster stopped this run's tasks (%s)",
                    " ".join(str(err).split()))


#: states of a worker's task that will not run its function any more
_SETTLED = ("memory", "error", "released", "forgotten", "missing", "rescheduled")


def _running(token: str, dask_worker=None) -> Optional[int]:
    """Tasks of the run ``token`` on this worker that run, or may still start: a cancelled
    task goes on until its function returns, and one queued here ("ready", "waiting",
    ...) may start before the scheduler's word to drop it arrives."""
    return sum(1 for key, task in dask_worker.state.tasks.items()
               if token in str(key) and task.state not in _SETTLED)
