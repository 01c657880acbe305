"""``hitops calibrate REF.ps TGT.ps --scheduler ADDRESS`` on MSv4 processing sets.

What is built so far (docs/msv4.md, "Distributed"): with ``--scheduler`` a processing
set's run sends each chunk's baseline batches to the dask cluster, as the MSv2 run does
(calibrate/batch_tasks.py); the stores are still read and written on the client.  The
groups must equal a one-process v4 run and the v2 run cell for cell, the stores' input
arrays stay byte for byte as they were, the kernels really ran on the workers (the
scheduler saw the tasks), and a run stopped mid-way leaves no group registered.
Cost: about 15 s here (a LocalCluster of 2 worker processes).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")
distributed = pytest.importorskip("distributed")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.calibrate.output_msv4 import DataGroupTransaction  # noqa: E402
from msv4_sets import file_digests  # noqa: E402
from test_msv4_calibrate import (METHODS, _input_digests, _v4_group,  # noqa: E402,F401
                                 assert_group_equals_column, converted, copies)

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as local:
        yield local


def _groups(ps: str):
    return json.loads((Path(ps) / "target_0" / "zarr.json").read_text())["attributes"][
        "data_groups"]


def test_cluster_run_writes_what_one_process_and_v2_write(copies, cluster, tmp_path):
    ref2, tgt2, ref4, tgt4 = copies
    one = tmp_path / "one.ps.zarr"
    shutil.copytree(tgt4, one)
    before, ref_before = _input_digests(tgt4), file_digests(Path(ref4))
    flags = dict(method=",".join(METHODS), no_verdict=True, chunk_rows=400)
    r2 = calibrate_flat(ref2, tgt2, **flags)
    r1 = calibrate_flat(ref4, str(one), **flags)
    rc = calibrate_flat(ref4, tgt4, scheduler=cluster.scheduler_address, **flags)
    assert rc["chunks"] == r1["chunks"] == r2["chunks"] > 1
    assert rc["wraps"] == r1["wraps"] == r2["wraps"]
    # the kernels ran on the workers
    assert "transfer_batch" in set(cluster.scheduler.task_prefixes)
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")
        for a, b in zip(_v4_group(tgt4, method), _v4_group(str(one), method)):
            np.testing.assert_array_equal(a, b, err_msg=method)   # bit for bit, NaN = NaN
    assert set(_groups(tgt4)) == {"base", *METHODS}
    assert _input_digests(tgt4) == before
    assert file_digests(Path(ref4)) == ref_before


def test_cluster_run_stopped_mid_way_registers_no_group(copies, cluster, monkeypatch):
    _, _, ref4, tgt4 = copies
    before = file_digests(Path(tgt4))
    calls = []
    write = DataGroupTransaction.write_chunk

    def fail_in_second_chunk(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return write(self, *args, **kwargs)

    monkeypatch.setattr(DataGroupTransaction, "write_chunk", fail_in_second_chunk)
    with pytest.raises(KeyboardInterrupt):
        calibrate_flat(ref4, tgt4, method="pwc,cfpt", no_verdict=True, chunk_rows=400,
                       scheduler=cluster.scheduler_address)
    assert len(calls) == 2
    assert set(_groups(tgt4)) == {"base"}
    assert file_digests(Path(tgt4)) == before
