"""The rest of the chain on MSv4 processing sets (issue 37): ``hitops simulate --format msv4``.

Truth: the Measurement Sets v2 the same call writes beside the stores.  Calibrating
the simulated processing sets must write what calibrating the v2 sets writes (the
phaseref scene: a target and a calibrator, so two partitions per band with the
partition scheme chosen); a store in the way is refused without --overwrite and left
as it was; a conversion that fails leaves no store.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.errors import OutputExistsError, SceneError  # noqa: E402
from hitops.io.msv4.layout import read_layout  # noqa: E402
from hitops.io.msv4.rows import PartitionReader  # noqa: E402
from hitops.io.msv4.store import open_store  # noqa: E402
from hitops.simulate import simulate  # noqa: E402
from hitops.simulate import msv4_out  # noqa: E402
from hitops.simulate.scene import load_scene_mapping  # noqa: E402
from msv4_sets import file_digests  # noqa: E402
from test_msv4_calibrate import METHODS, _v2_columns, _v4_group  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


def _phaseref(duration: float = 600):
    scene = load_scene_mapping("phaseref")[0]
    scene["observation"]["duration"] = duration
    return scene


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """The phaseref scene, 10 minutes, written with --format msv4 once, in time chunks of
    about 200 rows (so that the stores have several chunks, as a long run's do)."""
    root = tmp_path_factory.mktemp("simv4")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(msv4_out, "ROWS_PER_CHUNK", 200)
        return simulate(_phaseref(), root, format="msv4")


def test_time_chunks_hold_about_the_rows_asked_for():
    assert msv4_out.time_chunk(8) == 3572          # 28 baselines: 100,016 rows
    assert msv4_out.time_chunk(2) == 100_000
    assert msv4_out.time_chunk(1) == 100_000       # never a division by zero


def test_simulate_msv4_writes_both_formats_partitioned_and_chunked(simulated):
    for band in ("86", "230"):
        ps = simulated[f"{band}.ps.zarr"]
        assert ps == simulated[band].with_name(f"sim-{band}.ps.zarr") and ps.is_dir()
        root = json.loads((ps / "zarr.json").read_text())
        assert root["attributes"]["type"] == "processing_set"
        parts = sorted(p.name for p in ps.iterdir() if p.is_dir())
        assert parts == [f"sim-{band}_0", f"sim-{band}_1"]     # one per field
        layout = read_layout(open_store(ps))
        fields = [frozenset(c.field_id.tolist()) for p in layout.partitions
                  for c in PartitionReader(layout, p.name, "base").chunks(1 << 30)]
        assert sorted(fields, key=min) == [{0}, {1}]               # target, calibrator
        for part in parts:
            vis = json.loads((ps / part / "VISIBILITY" / "zarr.json").read_text())
            n_time, n_baseline = vis["shape"][:2]
            chunk = vis["chunk_grid"]["configuration"]["chunk_shape"][0]
            assert chunk == -(-200 // n_baseline) < n_time
    assert not [p for p in simulated["86"].parent.iterdir() if p.name.startswith(".")]


def test_calibrate_on_simulated_stores_equals_calibrate_on_the_v2_sets(simulated, tmp_path):
    names = [simulated[k] for k in ("86", "230", "86.ps.zarr", "230.ps.zarr")]
    for path in names:
        shutil.copytree(path, tmp_path / path.name)
    ref2, tgt2, ref4, tgt4 = (str(tmp_path / p.name) for p in names)
    flags = dict(tracker="antenna", chunk_rows=300, no_verdict=True, method=",".join(METHODS))
    r2 = calibrate_flat(ref2, tgt2, **flags)
    r4 = calibrate_flat(ref4, tgt4, **flags)
    assert len(r4["groups"]) == len(r2["groups"]) == 2
    assert [g["chunks"] for g in r4["groups"]] == [g["chunks"] for g in r2["groups"]]
    for method in METHODS:
        v4 = _v4_group(tgt4, method)
        v2 = _v2_columns(tgt2, f"{method.upper()}_DATA")
        for got, want in zip(v4[:3] + v4[4:], v2[:3] + v2[4:]):   # time, stations, flags
            np.testing.assert_array_equal(got, want)
        np.testing.assert_allclose(v4[3], v2[3], rtol=2e-7, atol=1e-6, err_msg=method)
    assert sorted(r4["data_groups"]["pwc"]["partitions"]) == ["sim-230_0", "sim-230_1"]


def test_an_existing_store_is_refused_without_overwrite(tmp_path):
    scene = _phaseref(120)
    first = simulate(scene, tmp_path, format="msv4")
    store = first["230.ps.zarr"]
    before = file_digests(store)
    with pytest.raises(OutputExistsError, match=r"sim-230\.ps\.zarr"):
        simulate(scene, tmp_path, format="msv4")
    assert file_digests(store) == before
    shutil.rmtree(first["86"])
    shutil.rmtree(first["230"])     # only the stores are in the way now
    with pytest.raises(OutputExistsError, match=r"sim-86\.ps\.zarr, .*sim-230\.ps\.zarr"):
        simulate(scene, tmp_path, format="msv4")
    assert file_digests(store) == before
    again = simulate(scene, tmp_path, format="msv4", overwrite=True, seed=99)
    assert again["230.ps.zarr"] == store and file_digests(store) != before


def test_a_failed_conversion_leaves_no_store(tmp_path, monkeypatch):
    """The second band's conversion fails: the first band's finished store is not
    renamed either, and no hidden store is left."""
    from xradio import measurement_set as xms

    real = xms.convert_msv2_to_processing_set
    calls = []

    def fail_second(in_file, out_file, **kwargs):
        calls.append(out_file)
        real(in_file, out_file, **kwargs)
        if len(calls) == 2:
            raise KeyboardInterrupt
    monkeypatch.setattr(xms, "convert_msv2_to_processing_set", fail_second)
    with pytest.raises(KeyboardInterrupt):
        simulate(_phaseref(120), tmp_path, format="msv4")
    assert len(calls) == 2
    assert sorted(p.name for p in tmp_path.iterdir() if "zarr" in p.name) == []


def test_an_unknown_format_is_one_line(tmp_path):
    with pytest.raises(SceneError, match="--format 'v3' is not one of ms, msv4"):
        simulate(_phaseref(120), tmp_path, format="v3")
    assert list(tmp_path.iterdir()) == []


# ---- hitops diagnose on processing sets -------------------------------------------------

#: summary.json entries that name the paths or time the run, not what it measured
NOT_MEASURED = ("ms", "ref_ms", "outputs", "timing_s")


def _measured(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in NOT_MEASURED}


@pytest.fixture(scope="module")
def calibrated_pairs(tmp_path_factory):
    """{scene: (v2 ref, v2 target, v4 ref, v4 target)}: the demo scene (one channel) and
    the wideband scene (two windows of 16 channels), 10 minutes, 3% of both bands'
    samples flagged before xradio converts them, then ``pwc`` run on both formats (its
    flags: the input's | not calibrated, so the reference's flags reach the target's)."""
    from msv4_sets import convert
    from test_msv4_calibrate import _flag_some

    out = {}
    for name in ("demo", "wideband"):
        scene = load_scene_mapping(name)[0]
        scene["observation"]["duration"] = 600
        root = tmp_path_factory.mktemp(f"diag-{name}")
        sets = simulate(scene, root)
        ref, tgt = sets[scene["bands"][0]["name"]], sets[scene["bands"][1]["name"]]
        _flag_some(ref, tgt)
        ref4, tgt4 = (convert(p, root / f"{p.stem}.ps.zarr") for p in (ref, tgt))
        for pair in ((ref, tgt), (ref4, tgt4)):
            calibrate_flat(str(pair[0]), str(pair[1]), method="pwc", no_verdict=True)
        out[name] = tuple(str(p) for p in (ref, tgt, ref4, tgt4))
    return out


@pytest.mark.parametrize("scene", ["demo", "wideband"])
def test_diagnose_on_a_store_equals_diagnose_on_its_v2_set(calibrated_pairs, tmp_path, scene):
    """The same summary.json, number for number: coherence per baseline and interval, the
    comparison PWC_DATA vs DATA, the reference band's wraps (--ref-ms), and the per-
    channel section of the wideband scene."""
    from hitops.diagnose.api import diagnose

    ref2, tgt2, ref4, tgt4 = calibrated_pairs[scene]
    runs = [diagnose(tgt, columns="DATA,PWC_DATA", ref_ms=ref, outdir=str(tmp_path / name))
            for name, ref, tgt in (("v2", ref2, tgt2), ("v4", ref4, tgt4))]
    v2 = json.loads((tmp_path / "v2" / "summary.json").read_text())
    # the warnings name the set: the store's name read as its v2 set's
    v4 = json.loads((tmp_path / "v4" / "summary.json").read_text().replace(tgt4, tgt2))
    assert _measured(v4) == _measured(v2)
    assert runs[1]["ms"] == tgt4
    assert v2["comparisons"] and (v2["spectral"] is not None) == (scene == "wideband")


def test_diagnose_refusals_on_a_store_are_one_line(calibrated_pairs, tmp_path):
    from hitops.diagnose.api import diagnose
    from hitops.errors import ColumnError, InputError

    tgt4 = calibrated_pairs["demo"][3]
    before = file_digests(Path(tgt4))
    with pytest.raises(ColumnError, match="has no data group 'cwu' \\(the column CWU_DATA\\)"):
        diagnose(tgt4, columns="DATA,CWU_DATA", outdir=None)
    with pytest.raises(InputError, match="keeps no CASA flag versions"):
        diagnose(tgt4, columns="DATA", outdir=None, restore_flags="hitops_original")
    assert file_digests(Path(tgt4)) == before


# ---- the run page (hitops report) of a run on processing sets ---------------------------

def test_report_shows_data_groups_and_checksums_of_the_input_groups(calibrated_pairs,
                                                                     tmp_path):
    """The page names each method's data group and its partitions, and the provenance holds
    a checksum of each store's input group (``base``), which a further run adding a group
    leaves as it was and a change of one visibility changes."""
    import subprocess
    import sys

    import zarr

    from hitops.report.provenance import checksums

    _, _, ref4, tgt4 = calibrated_pairs["demo"]
    for path in (ref4, tgt4):
        shutil.copytree(path, tmp_path / Path(path).name)
    ref, tgt = tmp_path / Path(ref4).name, tmp_path / Path(tgt4).name
    before = {c.path: c for c in checksums([ref, tgt])}
    calibrate_flat(str(ref), str(tgt), method="cfpt", no_verdict=True)   # report beside tgt
    after = {c.path: c for c in checksums([ref, tgt])}
    assert after == before and len(after) == 2
    assert before[str(ref)].sha256 != before[str(tgt)].sha256
    done = subprocess.run([str(Path(sys.executable).parent / "hitops"), "report", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    html = (tmp_path / "index.html").read_text()
    assert "data groups written: cfpt (partitions sim-230_0)" in html
    for c in after.values():
        assert f"<code>{c.sha256}</code>" in html and c.path in html
    assert "data group base (VISIBILITY + FLAG) of 1 partition(s)" in html
    vis = zarr.open_array(str(tgt / "sim-230_0" / "VISIBILITY"), mode="r+")
    vis[0, 0, 0, 0] = vis[0, 0, 0, 0] + 1
    assert checksums([tgt])[0].sha256 != before[str(tgt)].sha256
