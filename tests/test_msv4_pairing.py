"""A field of the target band that the reference band does not hold, on MSv2 and MSv4.

hitops pairs the bands' (field, window) groups by field name (hitops/calibrate/groups.py):
a field in one band only is left out with a warning naming it and the set, and the run
goes on with the fields both hold.  On processing sets a partition then has no partner:
the phaseref scene (M87 and its calibrator 3C273 in alternating scans, one partition
holding both), with the reference band's 3C273 rows taken out before the conversion.
Truth: the same run on the Measurement Sets v2; the left-out field's time steps of the
new data group stay as staged (NaN, flagged), the paired field's equal the v2 column.
Cost: about 15 s here.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.io import tables  # noqa: E402
from msv4_sets import convert  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


@pytest.fixture(scope="module")
def one_field_reference(tmp_path_factory):
    """(v2 reference holding M87 only, v2 target holding both, their processing sets)."""
    from casacore.tables import taql

    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    scene = load_scene_mapping("phaseref")[0]
    scene["observation"]["duration"] = 600
    root = tmp_path_factory.mktemp("pairing")
    sets = simulate(scene, root)
    full_ref, tgt = Path(sets["86"]), Path(sets["230"])
    ref = root / "ref-m87.ms"
    fields = tables.read_columns(str(full_ref), ["FIELD_ID"])["FIELD_ID"]
    m87 = int(np.bincount(fields).argmax())     # the target field has the longer scans
    taql(f"SELECT FROM '{full_ref}' WHERE FIELD_ID == {m87} GIVING '{ref}' AS PLAIN")
    return (str(ref), str(tgt), str(convert(ref, root / "ref.ps.zarr")),
            str(convert(tgt, root / "tgt.ps.zarr")))


def _group_arrays(ps: str, name: str):
    partition = next(p for p in Path(ps).iterdir() if (p / "zarr.json").exists())
    import zarr

    group = zarr.open_group(str(partition), mode="r")
    fields = np.asarray(group["field_name"][...]).astype(str)
    return fields, group[f"VISIBILITY_{name.upper()}"][...], group[f"FLAG_{name.upper()}"][...]


def test_a_field_without_partner_is_left_out_with_a_warning(one_field_reference, caplog):
    ref2, tgt2, ref4, tgt4 = one_field_reference
    flags = dict(method="pwc", no_verdict=True, chunk_rows=2000)
    with caplog.at_level(logging.WARNING, logger="hitops"):
        r2 = calibrate_flat(ref2, tgt2, **flags)
        r4 = calibrate_flat(ref4, tgt4, **flags)
    left_out = [r.getMessage() for r in caplog.records if "only: left out" in r.getMessage()]
    assert left_out == [f"field 3C273 is in {tgt2} only: left out",
                        f"field 3C273 is in {tgt4} only: left out"]
    assert r4["rows"] == r2["rows"] and r4["wraps"] == r2["wraps"]
    assert r4["data_groups"]["pwc"]["partitions"] == [Path(_group_partition(tgt4)).name]
    fields, vis, flag = _group_arrays(tgt4, "pwc")
    calibrator = np.char.startswith(fields, "3C273")
    assert calibrator.any() and (~calibrator).any()
    assert flag[calibrator].all() and np.isnan(vis[calibrator]).all()   # as staged
    assert not flag[~calibrator].all()
    # the paired field's cells hold what the v2 run wrote in its rows
    v2 = tables.read_columns(tgt2, ["FIELD_ID", "PWC_DATA", "FLAG"])
    m87_rows = v2["FIELD_ID"] == np.bincount(v2["FIELD_ID"]).argmax()
    present = np.isfinite(vis[~calibrator]).any(axis=(-1, -2))
    np.testing.assert_allclose(np.sort_complex(vis[~calibrator][present].ravel()),
                               np.sort_complex(v2["PWC_DATA"][m87_rows].ravel()),
                               rtol=2e-7, atol=1e-6)
    assert json.loads((Path(tgt4) / Path(_group_partition(tgt4)).name / "zarr.json")
                      .read_text())["attributes"]["data_groups"]["pwc"]["flag"] == "FLAG_PWC"


def _group_partition(ps: str) -> str:
    return str(next(p for p in Path(ps).iterdir() if (p / "zarr.json").exists()))
