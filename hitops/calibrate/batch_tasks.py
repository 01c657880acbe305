"""Where a chunk's baseline-group transfers run: this process's threads, or a dask cluster.

One interface for both (:class:`BatchTasks`): :meth:`~BatchTasks.start` hands the
groups' :class:`~hitops.calibrate.transfer.TransferInputs` over and returns at once,
:meth:`~BatchTasks.results` waits for their
:class:`~hitops.calibrate.transfer.TransferResult` in the same order.

* Threads (no ``--scheduler``): a pool of one thread per core that lives for the
  run.  The groups are independent and already cut to two per core, so a task graph
  would add nothing but its own work per chunk (building, culling and ordering it
  held the GIL for about 6 ms per chunk at 10^7 rows, py-spy), and dask's threaded
  ``get`` cannot return before the tasks end: the read of the next chunk could then
  only be asked for before the kernels start, and its getcol (which holds the GIL)
  would hold up their start.
* A cluster (``--scheduler``): the groups go to the dask.distributed client as
  delayed tasks computed together, as before; the tables are still read and written
  on this process (hitops/calibrate/pipeline.py says why).
* Inline (``n_threads`` 0, no client): in the calling thread, one group after the
  other: a chunk task on a dask worker (hitops/calibrate/worker_chunks.py), whose
  cores are the worker's own threads.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import List, Optional

from .transfer import TransferInputs, TransferResult, transfer_batch


class BatchTasks:
    """Runs one chunk's baseline-group transfers at a time (``client``: a dask.distributed
    Client, or None for ``n_threads`` threads of this process, 0: the calling thread)."""

    def __init__(self, client, n_threads: int):
        self.client = client
        self.inline = client is None and int(n_threads) == 0
        self._pool: Optional[ThreadPoolExecutor] = None
        if client is None and not self.inline:
            self._pool = ThreadPoolExecutor(max(1, int(n_threads)),
                                            thread_name_prefix="hitops-transfer")

    def start(self, inputs: List[TransferInputs]) -> "StartedGroups":
        """The groups' tasks, started (threads), run (inline) or ready to be computed
        (cluster)."""
        if self.inline:
            done = []
            for one in inputs:
                done.append(Future())
                done[-1].set_result(transfer_batch(one))
            return StartedGroups(done, None)
        if self._pool is not None:
            return StartedGroups([self._pool.submit(transfer_batch, i) for i in inputs], None)
        import dask

        return StartedGroups(None, [dask.delayed(transfer_batch, pure=False)(i) for i in inputs])

    def results(self, started: "StartedGroups") -> List[TransferResult]:
        """Each group's result, in the order the groups were started."""
        if started.futures is not None:
            try:
                return [f.result() for f in started.futures]
            finally:
                for f in started.futures:
                    f.cancel()
        import dask

        return list(dask.compute(*started.delayed, scheduler=self.client.get))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)


@dataclass(frozen=True)
class StartedGroups:
    """One chunk's group tasks: futures of this process's threads, or delayed cluster tasks."""

    futures: Optional[List[Future]]
    delayed: Optional[list]
