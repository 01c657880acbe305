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
from pathlib import Path

import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from msv4_sets import convert  # noqa: E402
from test_msv4_calibrate import (_flag_some, _input_digests,  # noqa: E402
                                 assert_group_equals_column)

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
def test_table_path_writes_the_v2_columns_as_data_groups(solved_store, tmp_path, flags):
    ref2, tgt2, tgt4, table = solved_store
    target2, target4 = tmp_path / "target.ms", tmp_path / "target.ps.zarr"
    shutil.copytree(tgt2, target2)
    shutil.copytree(tgt4, target4)
    before = _input_digests(str(target4))
    partitions = sorted(p for p in target4.iterdir() if (p / "zarr.json").exists())
    groups_before = {p.name: set(_groups(p)) for p in partitions}
    r2 = calibrate_flat(ref2, str(target2), reference_table=table, **flags)
    r4 = calibrate_flat(ref2, str(target4), reference_table=table, **flags)
    assert r4["chunks"] > 2
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
