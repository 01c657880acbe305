"""``hitops calibrate --reference-table`` with an MSv4 processing set as the target.

Truth: the same run on the Measurement Set v2 the store was converted from (the pair of
tests/solutions_scene.py: two 230 GHz windows of 16 channels, CASA fringefit's 4-s
solutions of the 86 GHz band).  Each method's data group must hold the v2 run's column
and FLAG cell for cell (to float32 rounding; 3% of the target's samples flagged), in chunks of few rows: a chunk of the table
path ends at a time step on a processing set (hitops/calibrate/table_store.py), and one
ending inside a step would blank that step's first cells when the next chunk is
written.  With the n0 step (``--offset-model point``), the integers the first pass over
the store solves are the v2 run's.  The store's input arrays stay as they were.
Cost: about 25 s here (fringefit, the conversion and four runs).
"""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.io.msv4.data_group import DataGroupWriter  # noqa: E402
from msv4_sets import convert, file_digests  # noqa: E402
from test_msv4_calibrate import (_flag_some, _input_digests,  # noqa: E402
                                 _v4_group, assert_group_equals_column)

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


@pytest.fixture(scope="module")
def solved_store(fringe_fitted, tmp_path_factory):
    """(v2 reference, v2 target, the target's processing set, fringefit's table): the
    session's pair, its target copied with 3% of the samples flagged before the conversion
    (the groups' flags carry them)."""
    pair, table = fringe_fitted
    root = tmp_path_factory.mktemp("v4table")
    target = root / "target.ms"
    shutil.copytree(pair.target_ms, target)
    _flag_some(target)
    return (str(pair.ref_ms), str(target), str(convert(target, root / "target.ps.zarr")),
            str(table))


@pytest.mark.parametrize("flags", [
    dict(method="pwc,cfpt", chunk_rows=100),
    dict(method="pwc", chunk_rows=250, offset_model="point"),
], ids=["pwc-cfpt-chunks", "pwc-n0"])
def test_table_path_writes_the_v2_columns_as_data_groups(solved_store, tmp_path, flags,
                                                         monkeypatch):
    ref2, tgt2, tgt4, table = solved_store
    target2, target4 = tmp_path / "target.ms", tmp_path / "target.ps.zarr"
    shutil.copytree(tgt2, target2)
    shutil.copytree(tgt4, target4)
    before = _input_digests(str(target4))
    partitions = sorted(p for p in target4.iterdir() if (p / "zarr.json").exists())
    groups_before = {p.name: set(_groups(p)) for p in partitions}
    r2 = calibrate_flat(ref2, str(target2), reference_table=table, **flags)
    real, writers = DataGroupWriter.write_cells, set()

    def on_which_thread(self, *args):
        writers.add(threading.current_thread().name)
        return real(self, *args)

    monkeypatch.setattr(DataGroupWriter, "write_cells", on_which_thread)
    r4 = calibrate_flat(ref2, str(target4), reference_table=table, **flags)
    assert r4["chunks"] > 2
    # the chunks are written on a thread of their own, beside the next read
    # (hitops/calibrate/chunk_io.py); the groups must equal the v2 columns all the same
    assert writers == {"hitops-write_0"}
    assert r4["samples"] == r2["samples"]
    assert r4.get("offsets") == r2.get("offsets")
    if "offset_model" in flags:
        assert any(k for solve in r4["offsets"]["solves"] for k in solve["k"].values())
    methods = flags["method"].split(",")
    assert set(r4["data_groups"]) == set(methods)
    for method in methods:
        assert_group_equals_column(str(target4), method, str(target2),
                                   f"{method.upper()}_DATA")
    assert _input_digests(str(target4)) == before
    assert r4["data_groups"][methods[0]]["partitions"] == [p.name for p in partitions]
    assert len(partitions) == 2     # the two target windows
    for partition in partitions:
        assert set(_groups(partition)) == groups_before[partition.name] | set(methods)


def _groups(partition: Path):
    return json.loads((partition / "zarr.json").read_text())["attributes"]["data_groups"]


# ---- --scheduler: the workers read, correct and write the chunks (table_workers.py;
# ``cluster``: tests/conftest.py)
@pytest.fixture(scope="module")
def sparse_store(solved_store, tmp_path_factory):
    """The target with one baseline's rows removed over the first half of the track before
    the conversion: its time steps hold fewer rows than baselines, so a chunk of the run
    covers more steps than a zarr chunk of the new groups, and neighbouring chunks share
    one (their writes must not run at once)."""
    from casacore import tables as pt

    _, tgt2, _, _ = solved_store
    root = tmp_path_factory.mktemp("v4table-sparse")
    target = root / "target.ms"
    with pt.table(tgt2, ack=False) as t:
        middle = float(np.median(t.getcol("TIME")))
        kept = t.query(f"NOT (ANTENNA1 == 0 AND ANTENNA2 == 1 AND TIME < {middle!r})")
        kept.copy(str(target), deep=True).close()
        kept.close()
    return str(convert(target, root / "target.ps.zarr"))


@pytest.mark.parametrize("store, flags", [
    ("full", dict(method="pwc,cfpt", chunk_rows=100)),
    ("full", dict(method="pwc", chunk_rows=250, offset_model="point")),
    ("sparse", dict(method="pwc,cfpt", chunk_rows=100)),
], ids=["pwc-cfpt", "pwc-n0", "sparse-shared-zarr-chunks"])
def test_cluster_table_run_writes_what_one_process_writes(solved_store, sparse_store, cluster,
                                                          tmp_path, store, flags):
    """Each chunk a task on any worker, in any order (the table path carries nothing from
    chunk to chunk), the n0 step's sums added on the client in chunk order: the groups
    equal the one-process run's bit for bit, with the same counts and integers."""
    from hitops.calibrate.table_store import StoreRows

    ref2, _, full, table = solved_store
    source = full if store == "full" else sparse_store
    one, on_cluster = tmp_path / "one.ps.zarr", tmp_path / "cluster.ps.zarr"
    shutil.copytree(source, one)
    shutil.copytree(source, on_cluster)
    before = _input_digests(str(on_cluster))
    r1 = calibrate_flat(ref2, str(one), reference_table=table, no_verdict=True, **flags)
    rc = calibrate_flat(ref2, str(on_cluster), reference_table=table, no_verdict=True,
                        scheduler=cluster.scheduler_address, **flags)
    assert rc["chunks"] == r1["chunks"] > 2
    assert rc["samples"] == r1["samples"] and rc.get("offsets") == r1.get("offsets")
    prefixes = set(cluster.scheduler.task_prefixes)
    assert "hitops-table-write" in prefixes
    if "offset_model" in flags:
        assert "hitops-table-sums" in prefixes
        assert any(k for solve in rc["offsets"]["solves"] for k in solve["k"].values())
    for method in flags["method"].split(","):
        for a, b in zip(_v4_group(str(on_cluster), method), _v4_group(str(one), method)):
            np.testing.assert_array_equal(a, b, err_msg=method)   # bit for bit, NaN = NaN
    assert _input_digests(str(on_cluster)) == before
    if store == "sparse":
        # the case the write order exists for: a chunk whose steps reach into the zarr
        # chunk its neighbour writes
        from hitops.calibrate.output_msv4 import DataGroupTransaction

        stored = StoreRows.of(str(one), ["DATA"], flags["chunk_rows"])
        tx = DataGroupTransaction(str(one), {"pwc": "X_DATA"}, "DATA", list(stored.sources),
                                  flags["chunk_rows"], overwrite=False)
        spans = [set(tx.zarr_chunks(*stored.step_span(k))) for k in range(stored.n_chunks)]
        assert any(a & b for a, b in zip(spans, spans[1:]))


def test_cluster_table_run_that_cannot_read_a_chunk_leaves_the_store_as_it_was(
        solved_store, cluster, tmp_path):
    """A damaged zarr chunk of the target's VISIBILITY: the worker's read fails with one
    line naming it, and the run leaves no group and every file as it was."""
    from hitops.errors import ProcessingSetError

    ref2, _, tgt4, table = solved_store
    target = tmp_path / "target.ps.zarr"
    shutil.copytree(tgt4, target)
    partition = sorted(p for p in target.iterdir() if (p / "zarr.json").exists())[1]
    damaged = next(f for f in sorted((partition / "VISIBILITY" / "c").rglob("*"))
                   if f.is_file())
    damaged.write_bytes(b"not a blosc frame" * 8)
    before = file_digests(target)
    with pytest.raises(ProcessingSetError, match=f"partition '{partition.name}', VISIBILITY "
                                                 r"of time steps .* the store is damaged"):
        calibrate_flat(ref2, str(target), reference_table=table, method="pwc,cfpt",
                       no_verdict=True, chunk_rows=100, scheduler=cluster.scheduler_address)
    for each in target.iterdir():
        if (each / "zarr.json").exists():
            assert not {"pwc", "cfpt"} & set(_groups(each))
    assert file_digests(target) == before


def test_scheduler_with_a_table_and_a_v2_target_is_refused_in_one_line(solved_store):
    from hitops.errors import InputError

    ref2, tgt2, _, table = solved_store
    with pytest.raises(InputError, match=r"^--scheduler tcp://127\.0\.0\.1:1 with "
                                         r"--reference-table .* and the Measurement Set v2 "
                                         r"target .*: .* drop --scheduler, or convert the "
                                         r"target to an MSv4 processing set"):
        calibrate_flat(ref2, tgt2, reference_table=table, scheduler="tcp://127.0.0.1:1")


def test_cluster_table_run_interrupted_registers_no_group(solved_store, cluster, tmp_path,
                                                         monkeypatch):
    """An interrupt on the client while the workers write (at the second chunk it takes
    back): the run's tasks are cancelled and waited for before the staged arrays are
    removed, so no write lands after the rollback and every file is as it was."""
    from hitops.calibrate import table_workers

    ref2, _, tgt4, table = solved_store
    target = tmp_path / "target.ps.zarr"
    shutil.copytree(tgt4, target)
    before = file_digests(target)
    taken = []

    class StopAtSecond(table_workers.Progress):
        def update(self, n: int = 1) -> None:
            taken.append(n)
            if len(taken) == 2:
                raise KeyboardInterrupt
            super().update(n)

    monkeypatch.setattr(table_workers, "Progress", StopAtSecond)
    with pytest.raises(KeyboardInterrupt):
        calibrate_flat(ref2, str(target), reference_table=table, method="pwc,cfpt",
                       no_verdict=True, chunk_rows=100, scheduler=cluster.scheduler_address)
    assert len(taken) == 2
    for each in target.iterdir():
        if (each / "zarr.json").exists():
            assert not {"pwc", "cfpt"} & set(_groups(each))
    assert file_digests(target) == before
