"""hitops/cluster.py: the client behind ``hitops calibrate --scheduler``.

No slurm here: a stand-in ``dask_jobqueue`` module whose SLURMCluster is a
distributed LocalCluster (in-process workers) records what hitops asks of it,
so the slurm path (arguments, scaling, waiting, closing) runs for real up to
sbatch.  The run against a real slurm is tests/test_cluster_slurm.py.
"""

from __future__ import annotations

import shutil
import sys
import types

import numpy as np
import pytest
from casacore import tables as pt

from hitops import cluster
from hitops.errors import InputError
from hitops.testing import PairSpec


@pytest.mark.parametrize("text, expected", [
    ("slurm", ("slurm", cluster.DEFAULT_SLURM_WORKERS)),
    ("slurm:3", ("slurm", 3)),
    ("SLURM:1", ("slurm", 1)),
    ("tcp://node001:8786", ("address", 0)),
    ("127.0.0.1:8786", ("address", 0)),
])
def test_parse_scheduler(text, expected):
    assert cluster.parse_scheduler(text) == expected


@pytest.mark.parametrize("text", ["slurm:0", "slurm:x", "slurm:"])
def test_bad_worker_count_is_one_clear_error(text):
    with pytest.raises(InputError, match="positive integer"):
        cluster.parse_scheduler(text)


def test_unreachable_address_names_the_remedy():
    import dask
    import distributed  # noqa: F401  registers its defaults before the set() below
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        with pytest.raises(InputError, match="cannot reach a dask scheduler.*--scheduler slurm"):
            cluster.dask_client("tcp://127.0.0.1:9")


def test_slurm_without_dask_jobqueue_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)   # import fails
    with pytest.raises(InputError, match=r"pip install 'hitops\[hpc\]'"):
        cluster.dask_client("slurm")


def _stand_in_jobqueue(monkeypatch, *, start_workers=True):
    """A dask_jobqueue module whose SLURMCluster starts in-process workers."""
    from distributed import LocalCluster

    record = {"kwargs": None, "scaled": [], "closed": 0}

    class SLURMCluster(LocalCluster):
        def __init__(self, **kwargs):
            record["kwargs"] = kwargs
            super().__init__(n_workers=0, processes=False, threads_per_worker=1,
                             dashboard_address=None)

        def job_script(self):
            return "#!/bin/bash\n#SBATCH -J dask-worker\n"

        def scale(self, n=None, jobs=0, **kw):
            record["scaled"].append(jobs)
            if start_workers:
                super().scale(jobs)

        def close(self, *a, **kw):
            record["closed"] += 1
            return super().close(*a, **kw)

    module = types.SimpleNamespace(SLURMCluster=SLURMCluster)
    monkeypatch.setitem(sys.modules, "dask_jobqueue", module)
    monkeypatch.setattr(cluster.shutil, "which", lambda name: f"/usr/bin/{name}")
    return record


def test_slurm_starts_n_single_core_workers_and_closes_them(monkeypatch):
    record = _stand_in_jobqueue(monkeypatch)
    client, closer = cluster.dask_client("slurm:2")
    try:
        assert len(client.scheduler_info()["workers"]) == 2
        assert record["scaled"] == [2]
        kw = record["kwargs"]
        assert kw["cores"] == 1 and kw["processes"] == 1
        assert kw["memory"] == cluster.DEFAULT_MEMORY and kw["python"] == sys.executable
    finally:
        closer.close()
    assert record["closed"] >= 1
    assert client.status == "closed"


def test_slurm_keeps_what_jobqueue_configuration_sets(monkeypatch):
    import dask
    record = _stand_in_jobqueue(monkeypatch)
    with dask.config.set({"jobqueue.slurm.memory": "16GB", "jobqueue.slurm.cores": 4}):
        client, closer = cluster.dask_client("slurm:1")
        closer.close()
    assert "memory" not in record["kwargs"] and "cores" not in record["kwargs"]


def test_slurm_jobs_that_never_start_are_cancelled(monkeypatch):
    record = _stand_in_jobqueue(monkeypatch, start_workers=False)
    monkeypatch.setenv("HITOPS_SLURM_WAIT", "1")
    with pytest.raises(InputError, match="0 of 2 dask worker job.*HITOPS_SLURM_WAIT"):
        cluster.dask_client("slurm")
    assert record["closed"] == 1


def test_slurm_without_sbatch_is_one_clear_error(monkeypatch):
    _stand_in_jobqueue(monkeypatch)
    monkeypatch.setattr(cluster.shutil, "which",
                        lambda name: None if name == "sbatch" else f"/usr/bin/{name}")
    with pytest.raises(InputError, match="sbatch not found on PATH"):
        cluster.dask_client("slurm")


@pytest.mark.slow
def test_calibrate_with_scheduler_slurm_matches_threads(tmp_path, new_pair, monkeypatch):
    """hitops calibrate --scheduler slurm:2 through the stand-in: the api.py hook runs
    the transfer on the cluster's workers and writes the threaded run's output."""
    from hitops.calibrate import calibrate_flat

    truth = new_pair(PairSpec(n_time=120, seed=41, n_scans=2))
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copytree(truth.ref_ms, copy / "ref.ms")
    shutil.copytree(truth.target_ms, copy / "target.ms")
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    record = _stand_in_jobqueue(monkeypatch)
    calibrate_flat(copy / "ref.ms", copy / "target.ms", method="pwc,cfpt", scheduler="slurm:2")
    assert record["scaled"][0] == 2 and record["closed"] >= 1
    for c in ("PWC_DATA", "CFPT_DATA", "FLAG"):
        with pt.table(str(truth.target_ms), ack=False) as a, \
                pt.table(str(copy / "target.ms"), ack=False) as b:
            assert np.array_equal(a.getcol(c), b.getcol(c)), c


def test_a_default_client_of_the_caller_gets_no_work_without_scheduler(tmp_path, new_pair):
    """A Python caller with a dask.distributed Client as the default scheduler: a run
    without --scheduler keeps every read (dask-ms's own included) on its own threads,
    and its output is that of a run without the client."""
    from distributed import Client, LocalCluster

    from hitops.calibrate import calibrate_flat

    truth = new_pair(PairSpec(n_time=120, seed=43, n_scans=2))
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copytree(truth.ref_ms, copy / "ref.ms")
    shutil.copytree(truth.target_ms, copy / "target.ms")
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", no_verdict=True)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        calibrate_flat(copy / "ref.ms", copy / "target.ms", method="pwc", no_verdict=True)
        # the scheduler keeps a prefix entry for every kind of task it was ever sent
        received = client.run_on_scheduler(
            lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
    assert received == []
    for c in ("PWC_DATA", "FLAG"):
        with pt.table(str(truth.target_ms), ack=False) as a, \
                pt.table(str(copy / "target.ms"), ack=False) as b:
            assert np.array_equal(a.getcol(c), b.getcol(c)), c
