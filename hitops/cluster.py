"""The dask.distributed client behind ``hitops calibrate --scheduler``.

``--scheduler`` takes either

* the address of a running dask scheduler (``tcp://host:8786``): connect to it;
* ``slurm`` or ``slurm:N``: start a scheduler in this process and N dask
  workers (default 2) as slurm batch jobs through dask-jobqueue's
  ``SLURMCluster`` (``pip install 'hitops[hpc]'``), wait until they have
  joined, and cancel the jobs afterwards.

The worker jobs' resources come from dask-jobqueue's own configuration
(``jobqueue.slurm.*`` in ``~/.config/dask/jobqueue.yaml`` or
``DASK_JOBQUEUE__SLURM__MEMORY=8GB`` and the like: queue, account, walltime,
job-extra-directives, ...).  Where that configuration leaves them unset, each
job is one single-threaded worker with ``DEFAULT_MEMORY``.  The jobs run this
process's Python (``sys.executable``), so login and compute nodes must share
the environment (same path, or the same container image).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
from typing import Iterator, Optional, Tuple

from .errors import InputError

log = logging.getLogger("hitops.cluster")

#: workers started by a bare ``--scheduler slurm``
DEFAULT_SLURM_WORKERS = 2
#: memory per worker job when jobqueue.slurm.memory is not configured
DEFAULT_MEMORY = "4GB"
#: seconds to wait for the worker jobs to start (HITOPS_SLURM_WAIT overrides)
DEFAULT_WAIT = 300.0


def parse_scheduler(scheduler: str) -> Tuple[str, int]:
    """("slurm", N) for ``slurm``/``slurm:N``, else ("address", 0)."""
    text = scheduler.strip()
    kind, sep, count = text.partition(":")
    if kind.lower() != "slurm":
        return "address", 0
    if not sep:
        return "slurm", DEFAULT_SLURM_WORKERS
    try:
        n = int(count)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(f"--scheduler {scheduler}: the worker count after 'slurm:' must be a "
                         f"positive integer (e.g. slurm:4)")
    return "slurm", n


@contextlib.contextmanager
def scheduler_client(scheduler: str) -> Iterator[Optional[object]]:
    """The client of ``--scheduler`` for the block, closed after it (with whatever was
    started for it); None when ``scheduler`` is empty (the run uses its own threads)."""
    if not scheduler:
        yield None
        return
    client, closer = dask_client(scheduler)
    with closer:
        yield client


def dask_client(scheduler: str):
    """(client, closer) for ``--scheduler``; ``closer.close()`` closes the client and
    whatever was started for it (the slurm worker jobs are cancelled)."""
    kind, n_workers = parse_scheduler(scheduler)
    stack = contextlib.ExitStack()
    try:
        if kind == "address":
            client = _connect(scheduler)
            stack.callback(client.close)
        else:
            client = _slurm_client(scheduler, n_workers, stack)
    except BaseException:   # Ctrl-C while waiting for the jobs included: cancel them
        stack.close()
        raise
    return client, stack


def _connect(address: str):
    from distributed import Client
    try:
        return Client(address, set_as_default=False)
    except OSError as err:
        raise InputError(f"--scheduler {address}: cannot reach a dask scheduler there "
                         f"({err}); start one (dask scheduler), use --scheduler slurm, "
                         f"or omit the option") from err


def _slurm_client(scheduler: str, n_workers: int, stack: contextlib.ExitStack):
    try:
        import dask
        from dask_jobqueue import SLURMCluster
    except ImportError as err:
        raise InputError(f"--scheduler {scheduler} needs dask-jobqueue ({err}): "
                         f"pip install 'hitops[hpc]'") from err
    missing = [c for c in ("sbatch", "squeue", "scancel") if shutil.which(c) is None]
    if missing:
        raise InputError(f"--scheduler {scheduler}: {', '.join(missing)} not found on PATH; "
                         f"run on a slurm login node, or give a scheduler address")
    kwargs = {}
    # dask-jobqueue insists on cores and memory; keep whatever its configuration sets
    if dask.config.get("jobqueue.slurm.cores", None) is None:
        kwargs["cores"] = 1
    if dask.config.get("jobqueue.slurm.memory", None) is None:
        kwargs["memory"] = DEFAULT_MEMORY
    if dask.config.get("jobqueue.slurm.processes", None) is None:
        kwargs["processes"] = 1
    # the jobs start this interpreter, so they import the same hitops
    if dask.config.get("jobqueue.slurm.python", None) is None:
        kwargs["python"] = sys.executable
    try:
        cluster = SLURMCluster(**kwargs)
    except (OSError, ValueError, RuntimeError) as err:
        raise InputError(f"--scheduler {scheduler}: dask-jobqueue could not start its "
                         f"scheduler ({err})") from err
    stack.callback(cluster.close)
    log.info("slurm: submitting %d dask worker job(s) through dask-jobqueue (sbatch)", n_workers)
    log.debug("dask worker job script:\n%s", cluster.job_script())
    try:
        cluster.scale(jobs=n_workers)
    except Exception as err:   # sbatch refused: the message says why (partition, limits)
        raise InputError(f"--scheduler {scheduler}: sbatch refused the dask worker jobs "
                         f"({err}); check jobqueue.slurm.* (queue, account, memory)") from err

    from distributed import Client
    client = Client(cluster, set_as_default=False)
    stack.callback(client.close)   # LIFO: the client closes before its cluster
    wait = float(os.environ.get("HITOPS_SLURM_WAIT", DEFAULT_WAIT))
    try:
        client.wait_for_workers(n_workers, timeout=wait)
    except (TimeoutError, OSError) as err:
        have = len(client.scheduler_info().get("workers", {}))
        raise InputError(f"--scheduler {scheduler}: {have} of {n_workers} dask worker job(s) "
                         f"started within {wait:g} s (still queued? see squeue and the jobs' "
                         f"slurm-*.out); set HITOPS_SLURM_WAIT or ask for fewer workers") from err
    log.info("slurm: %d dask worker(s) running (scheduler %s)", n_workers,
             cluster.scheduler_address)
    return client
