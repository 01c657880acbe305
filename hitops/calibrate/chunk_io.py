"""One background thread that reads a group's chunks and writes their outputs, in order.

python-casacore holds the GIL for the whole of each getcol and putcol call, so a
read or a write blocks every Python thread for its length; only the numba kernels
(nogil) run beside it.  The chunk loop of :mod:`hitops.calibrate.pipeline` therefore
gives the table I/O to this one thread and keeps the main thread for starting the
transfer kernels:

* the read of chunk k+1 is asked for once chunk k's kernels have started (or
  before tracking, for a tracker that tracks the chunk itself), so the kernels do
  not wait for the GIL behind a getcol;
* the write of chunk k is queued behind that read and runs while chunk k+1's
  kernels run, instead of between the two transfers.

The thread takes the jobs in the order they are asked for, so a read and a write
never touch the target table at the same time, and the write of chunk k ends before
the read of chunk k+2 starts: at most two chunks' columns are held at once, as the
memory budget assumes (hitops/calibrate/memory.py).

Outputs that go to a zarr store (``writes_apart``: MSv4 data groups, new arrays
that no read of the run touches) are written on a second thread of their own, so
that chunk k+1's read runs beside chunk k-1's write instead of after it (zarr
decodes, encodes and stores on its own threads; the two calls only wait for them).
The memory budget then counts the chunk being written as well
(:func:`hitops.calibrate.memory.rows_for_budget`, ``writes_apart``); a write still
waits for the previous one, so the outputs are written in chunk order.

A failed read or write raises in the main thread at the next call that waits on it,
and at :meth:`close` at the latest, so nothing is committed after a failed write.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Dict, Optional


class ChunkIO:
    """Reads (``read(k) -> chunk``) and writes of one pass over ``n_chunks`` chunks;
    ``writes_apart``: the writes on a thread of their own (outputs to a zarr store)."""

    def __init__(self, read: Callable[[int], object], n_chunks: int,
                 writes_apart: bool = False):
        self._read, self.n_chunks = read, n_chunks
        # one chunk: nothing to overlap, so the reads and writes run on the calling
        # thread (a paper-size read's getcols took 0.12-0.15 s of CPU there against
        # 0.16-0.31 s on a fresh thread, measured; the cause is not pinned down)
        self._pool = (ThreadPoolExecutor(1, thread_name_prefix="hitops-io")
                      if n_chunks > 1 else None)
        self._writer = (ThreadPoolExecutor(1, thread_name_prefix="hitops-write")
                        if self._pool is not None and writes_apart else None)
        self._reads: Dict[int, Future] = {}
        self._write: Optional[Future] = None

    def _submit(self, fn: Callable, *args) -> Future:
        if self._pool is not None:
            return self._pool.submit(fn, *args)
        done: Future = Future()
        try:
            done.set_result(fn(*args))
        except BaseException as err:   # noqa: B036 - raised where the result is taken
            done.set_exception(err)
        return done

    def read_ahead(self, k: int) -> None:
        """Ask for chunk ``k`` (nothing when there is no such chunk or it is asked for)."""
        if 0 <= k < self.n_chunks and k not in self._reads:
            self._reads[k] = self._submit(self._read, k)

    def chunk(self, k: int):
        """Chunk ``k``, read (asked for now if it was not)."""
        self.read_ahead(k)
        return self._reads.pop(k).result()

    def write(self, fn: Callable, *args) -> None:
        """Queue ``fn(*args)`` after what is asked for so far; the previous write's error,
        if it failed, raises here."""
        self._wait_write()
        self._write = (self._writer.submit(fn, *args) if self._writer is not None
                       else self._submit(fn, *args))

    def _wait_write(self) -> None:
        pending, self._write = self._write, None
        if pending is not None:
            pending.result()

    def close(self, cancel: bool = False) -> None:
        """Wait for every job; the last write's error raises here.  ``cancel``: drop the
        jobs that have not started (a run that is failing rolls back anyway)."""
        try:
            if cancel:
                for pending in [*self._reads.values(), self._write]:
                    if pending is not None:
                        pending.cancel()
            if self._write is not None and not self._write.cancelled():
                self._wait_write()
        finally:
            self._reads.clear()
            self._write = None
            for pool in (self._pool, self._writer):
                if pool is not None:
                    pool.shutdown(wait=True)

    def __enter__(self) -> "ChunkIO":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        # already failing: wait for the job that runs (the transaction rolls back after
        # it), and let the error in flight be the one that is raised
        try:
            self.close(cancel=True)
        except BaseException:   # noqa: B036
            pass
