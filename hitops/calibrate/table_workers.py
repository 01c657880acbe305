"""Stage 4 of ``hitops calibrate --reference-table`` on a cluster: the workers read,
correct and write the chunks of an MSv4 processing set target.

The table path carries nothing from one chunk to the next: each row is corrected by the
table's antenna terms at its own time (hitops/calibrate/table_source.py).  So, unlike
the visibility path's chain (hitops/calibrate/worker_chunks.py, where chunk k+1's
tracking waits for chunk k's), each chunk is one task that may run on any worker at
any time:

* the writing pass: ``hitops-table-write`` reads chunk k of the target store
  (:meth:`StoreRows.read <hitops.calibrate.table_store.StoreRows.read>`, by path),
  corrects it by every method, writes its cells of the staged data groups and hands
  back its sample counts;
* the n0 step's first pass: ``hitops-table-sums`` reads and corrects chunk k and hands
  back its per-edge sums, which the client adds in chunk order, the additions one
  process makes in the same order (hitops/calibrate/from_table.py, ``offset_step``).

The one order kept is between writes that share a zarr chunk of the staged arrays
(a chunk of the run may end inside one: zarr reads such a chunk, changes it and writes
it back, so two at once would lose one's cells): a write waits for the last one
submitted into any of its zarr chunks (:meth:`DataGroupTransaction.zarr_chunks`).  The
client sends the plan once (:class:`TableJob`), keeps a few chunks in flight
(:func:`~hitops.calibrate.worker_chunks.in_flight`), and commits after every write has
returned.  A failure on a worker or an interrupt here cancels the run's tasks and waits
until none runs before the transaction removes the staged arrays.
"""

from __future__ import annotations

import logging
import uuid
from collections import deque
from dataclasses import dataclass
from typing import Callable, Deque, Dict, Optional, Tuple

from ..logs import Progress
from ..solutions.api import PreparedTransfer
from .table_chunks import (SampleCounts, TableRun, chunk_sums, correct_and_flag, merge_sums,
                           n0_column, read_chunk)
from .output_msv4 import DataGroupTransaction
from .worker_chunks import in_flight, stop_tasks

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class TableJob:
    """What every chunk task of a table run needs, sent to each worker once (the
    transaction is the worker's copy: it writes cells, the client keeps the record)."""

    run: TableRun
    transfers: Dict[str, PreparedTransfer]
    tx: Optional[DataGroupTransaction] = None     # None: the n0 step's first pass


# ---- the tasks (run on the workers)
def write_task(job: TableJob, k: int, *after) -> SampleCounts:
    """Chunk ``k`` read, corrected and written into its cells of the staged groups; its
    sample counts.  ``after``: the earlier writes into its zarr chunks (only waited for)."""
    chunk = read_chunk(job.run, k, None)
    done = correct_and_flag(job.run, job.transfers, chunk)
    job.tx.write_outputs(chunk.rows, done.outputs, done.new_flag)
    counts = SampleCounts()
    counts.add(done.before, done.new_flag)
    return counts


def sums_task(job: TableJob, k: int) -> Dict:
    """Chunk ``k``'s sums for the n0 step (the counted transfer, ``pwc``)."""
    return chunk_sums(job.run, job.transfers["pwc"], read_chunk(job.run, k, n0_column(job.run)))


# ---- the client's side
def write_on_workers(client, run: TableRun, tx: DataGroupTransaction,
                     transfers: Dict[str, PreparedTransfer]) -> SampleCounts:
    """The writing pass on the cluster: every chunk corrected and written by a worker;
    the run's sample counts."""
    counts = SampleCounts()
    # the last write into each zarr chunk, kept for the whole pass: a partition holding
    # several fields comes back to its first zarr chunks with the next field's chunks
    # (each future holds a few bytes on its worker)
    last_write: Dict[Tuple[str, int], object] = {}

    def submit(submit_one: Callable, k: int):
        shared = tx.zarr_chunks(*run.store.step_span(k))
        after = list(dict.fromkeys(last_write[c] for c in shared if c in last_write))
        future = submit_one(write_task, k, *after)
        last_write.update({c: future for c in shared})
        return future

    _each_chunk(client, run, TableJob(run, transfers, tx), "write", submit, counts.merge,
                "writing pass")
    for source in run.store.sources:
        tx.mark_written(source)
    return counts


def sums_on_workers(client, run: TableRun, prepared: PreparedTransfer) -> Dict:
    """The n0 step's first pass on the cluster: the run's sums, each chunk's added in
    chunk order."""
    sums: Dict = {}
    _each_chunk(client, run, TableJob(run, {"pwc": prepared}), "sums",
                lambda submit_one, k: submit_one(sums_task, k),
                lambda part: merge_sums(sums, part), "first pass (n0 step)")
    return sums


def _each_chunk(client, run: TableRun, job: TableJob, step: str, submit: Callable,
                collect: Callable, what: str) -> None:
    """Every chunk's task submitted (``submit(submit_one, k)``), a few ahead of the
    oldest unfinished one, whose result goes to ``collect`` in chunk order."""
    token = uuid.uuid4().hex[:12]
    scattered = client.scatter(job, broadcast=True, hash=False)
    workers = sorted(client.scheduler_info()["workers"])
    window = in_flight(len(workers))
    progress = (Progress(f"calibrate --reference-table {what} on {len(workers)} workers: "
                         "chunks", run.n_chunks, logger=log) if run.n_chunks > 1 else None)
    flight: Deque[object] = deque()

    def submit_one(k: int) -> Callable:
        def on_worker(fn, *args):
            # chunk k on the k-th worker in turn (others allowed): the reads spread evenly
            return client.submit(fn, scattered, *args, key=f"hitops-table-{step}-{token}-{k}",
                                 priority=-k, workers=[workers[k % len(workers)]],
                                 allow_other_workers=True)
        return on_worker

    try:
        for k in range(run.n_chunks):
            flight.append(submit(submit_one(k), k))
            while len(flight) > (window if k + 1 < run.n_chunks else 0):
                collect(flight.popleft().result())
                if progress is not None:
                    progress.update()
    except BaseException:
        stop_tasks(client, token, list(flight))
        raise

