"""``hitops calibrate REF.ps TGT.ps --scheduler ADDRESS`` on MSv4 processing sets.

With ``--scheduler`` and both bands processing sets, the workers read, track,
transfer and write each chunk themselves (hitops/calibrate/worker_chunks.py).  The
groups must equal a one-process v4 run bit for bit and the v2 run cell for cell (the
count tracker in several chunks; the antenna tracker and the wideband scene with the
n0 step, whose first pass's sums come back from the workers), the stores' input
arrays stay byte for byte as they were, the chunk tasks really ran on the workers and
the client's transfer batches did not, and a run that fails on a worker (a damaged
chunk of the store) or is interrupted on the client leaves no group registered and
every file of the store as it was.  Cost: about 30 s here (a LocalCluster of 2
worker processes).
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
from msv4_sets import file_digests  # noqa: E402
from hitops.calibrate import worker_chunks  # noqa: E402
from hitops.errors import ProcessingSetError  # noqa: E402
from test_msv4_calibrate import (METHODS, SPEC, _flag_some, _input_digests,  # noqa: E402,F401
                                 _v4_group, assert_group_equals_column, converted, copies,
                                 scenes)

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


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
    # the workers read, advanced and wrote the chunks; no batch went out from the client
    prefixes = set(cluster.scheduler.task_prefixes)
    assert {"hitops-read", "hitops-advance", "hitops-write"} <= prefixes
    assert "transfer_batch" not in prefixes
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")
        for a, b in zip(_v4_group(tgt4, method), _v4_group(str(one), method)):
            np.testing.assert_array_equal(a, b, err_msg=method)   # bit for bit, NaN = NaN
    assert set(_groups(tgt4)) == {"base", *METHODS}
    assert _input_digests(tgt4) == before
    assert file_digests(Path(ref4)) == ref_before


@pytest.mark.parametrize("scene, flags", [
    ("count", dict(tracker="count", offset_model="point", chunk_rows=400)),
    ("antenna", dict(tracker="antenna", offset_model="point", chunk_rows=700)),
    ("wideband", dict(offset_model="point", chunk_rows=600)),
])
def test_cluster_n0_step_writes_what_one_process_writes(copies, scenes, cluster, tmp_path,
                                                        scene, flags):
    """The n0 step's first pass sums on the workers; the client solves; the writing pass
    runs there again: a segmented tracker, and two windows of 16 channels (per-channel
    ratios, two partitions)."""
    if scene == "wideband":
        for path in scenes[scene][2:]:
            shutil.copytree(path, tmp_path / "wide" / Path(path).name)
        ref4, tgt4 = (str(tmp_path / "wide" / Path(p).name) for p in scenes[scene][2:])
    else:
        _, _, ref4, tgt4 = copies
    one = tmp_path / "one.ps.zarr"
    shutil.copytree(tgt4, one)
    flags = dict(method=",".join(METHODS), no_verdict=True, **flags)
    r1 = calibrate_flat(ref4, str(one), **flags)
    with distributed.Client(cluster) as client, distributed.get_task_stream(client) as stream:
        rc = calibrate_flat(ref4, tgt4, scheduler=cluster.scheduler_address, **flags)
    if scene == "wideband":   # the two windows' chains ran at once
        assert _overlapping_chains(stream.data)
    steps = [[g["offset_step"] for g in r.get("groups", [r])] for r in (rc, r1)]
    assert all(s["applied_to"] == ["pwc", "cwu"] for s in steps[0])
    assert [g["samples"] for g in rc.get("groups", [rc])] == \
        [g["samples"] for g in r1.get("groups", [r1])]
    # the antenna tracker's one-process run keeps its first pass and shifts it by the
    # step's integers; the cluster runs the writing pass again (the output stays on the
    # workers): the same integers, the values equal to float32 rounding
    exact = scene != "antenna"
    if exact:
        assert steps[0] == steps[1]
    else:
        assert [[(a["antenna"], a["k"]) for a in s["antennas"]] for s in steps[0]] == \
            [[(a["antenna"], a["k"]) for a in s["antennas"]] for s in steps[1]]
    for method in METHODS:
        cluster_run, one_run = _v4_group(tgt4, method), _v4_group(str(one), method)
        for a, b in zip(cluster_run[:3] + cluster_run[4:], one_run[:3] + one_run[4:]):
            np.testing.assert_array_equal(a, b, err_msg=method)
        if exact:   # bit for bit, NaN = NaN
            np.testing.assert_array_equal(cluster_run[3], one_run[3], err_msg=method)
        else:
            np.testing.assert_allclose(cluster_run[3], one_run[3], rtol=2e-7, atol=1e-6,
                                       err_msg=method)


def _overlapping_chains(records) -> bool:
    """Whether the advance tasks of two passes (each pass's tasks share a token) ran at
    overlapping times."""
    spans = {}
    for record in records:
        key = str(record["key"])
        if key.startswith("hitops-advance-"):
            token = key.split("-")[2]
            for part in record["startstops"]:
                lo, hi = spans.get(token, (np.inf, -np.inf))
                spans[token] = (min(lo, part["start"]), max(hi, part["stop"]))
    ordered = sorted(spans.values())
    return any(b[0] < a[1] for a, b in zip(ordered, ordered[1:]))


def _chunked_copy(converted, tmp_path, step: int):
    """The pair's target converted again with zarr chunks of ``step`` time steps."""
    from xradio.measurement_set import convert_msv2_to_processing_set

    _, tgt2, ref4, _ = converted
    tgt4 = tmp_path / "tgt.ps.zarr"
    convert_msv2_to_processing_set(tgt2, str(tgt4), main_chunksize={"time": step})
    return ref4, str(tgt4)


def test_a_worker_that_cannot_read_a_chunk_rolls_the_run_back(converted, cluster, tmp_path):
    """A damaged zarr chunk of the target's VISIBILITY (the fourth of five): the worker's
    read fails with one line naming it, the chunks before it may have been written, and
    the run leaves no group and every file as it was."""
    ref4, tgt4 = _chunked_copy(converted, tmp_path, 66)
    partition = next(p.name for p in Path(tgt4).iterdir() if p.is_dir())
    damaged = Path(tgt4) / partition / "VISIBILITY" / "c" / "3" / "0" / "0" / "0"
    damaged.write_bytes(b"not a blosc frame" * 8)
    before = file_digests(Path(tgt4))
    with pytest.raises(ProcessingSetError, match=r"VISIBILITY of time steps 198-263 cannot be "
                                                 r"read .* the store is damaged"):
        calibrate_flat(ref4, tgt4, method="pwc,cfpt", no_verdict=True, chunk_rows=400,
                       scheduler=cluster.scheduler_address)
    assert set(_groups(tgt4)) == {"base"}
    assert file_digests(Path(tgt4)) == before


def test_cluster_run_stopped_mid_way_registers_no_group(converted, cluster, tmp_path,
                                                       monkeypatch):
    """An interrupt on the client while the workers write: their tasks are cancelled and
    waited for before the staged arrays are removed."""
    ref4, tgt4 = _chunked_copy(converted, tmp_path, 66)
    before = file_digests(Path(tgt4))
    calls = []
    finish = worker_chunks._finish

    def stop_at_second_write(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return finish(*args)

    monkeypatch.setattr(worker_chunks, "_finish", stop_at_second_write)
    with pytest.raises(KeyboardInterrupt):
        calibrate_flat(ref4, tgt4, method="pwc,cfpt", no_verdict=True, chunk_rows=100,
                       scheduler=cluster.scheduler_address)
    assert len(calls) == 2
    assert set(_groups(tgt4)) == {"base"}
    assert file_digests(Path(tgt4)) == before


def test_a_failure_in_one_window_stops_the_other_and_rolls_back(scenes, cluster, tmp_path):
    """The wideband scene's two target windows (two partitions) run at once on the
    workers; a damaged chunk in the second stops the first at its next chunk, the error
    named is the damage (not the stop), and every file of the store stays as it was."""
    for path in scenes["wideband"][2:]:
        shutil.copytree(path, tmp_path / Path(path).name)
    ref4, tgt4 = (str(tmp_path / Path(p).name) for p in scenes["wideband"][2:])
    partitions = sorted(p.name for p in Path(tgt4).iterdir() if p.is_dir())
    assert len(partitions) == 2
    damaged = Path(tgt4) / partitions[1] / "VISIBILITY" / "c" / "0" / "0" / "0" / "0"
    damaged.write_bytes(b"not a blosc frame" * 8)
    before = file_digests(Path(tgt4))
    with pytest.raises(ProcessingSetError, match=f"partition '{partitions[1]}', VISIBILITY"):
        calibrate_flat(ref4, tgt4, method="pwc,cfpt,cwu", no_verdict=True, chunk_rows=200,
                       scheduler=cluster.scheduler_address)
    for partition in partitions:
        groups = json.loads((Path(tgt4) / partition / "zarr.json").read_text())[
            "attributes"]["data_groups"]
        assert set(groups) == {"base"}
    assert file_digests(Path(tgt4)) == before
