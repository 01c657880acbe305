"""``hitops calibrate`` on MSv4 processing sets equals the run on the v2 sets they came from.

Truth: the same run on the Measurement Sets v2 that xradio converted.  Each method's
new data group (hitops/calibrate/output_msv4.py) must hold the v2 run's output column
and its flags the v2 run's FLAG, cell for cell (to float32 rounding), for every
method, the count tracker cut into several chunks and the antenna tracker with the
n0 step (--offset-model point); the input's arrays stay byte for byte as they were.
A taken group name is refused without --overwrite, a run stopped in the middle of
a chunk leaves every file of the store as it was, and the modes the MSv4 path does
not take are one line each.  Cost: about 20 s here (the EHT import is shared with
tests/test_realdata.py).
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
from hitops.errors import ColumnError, InputError, OutputExistsError  # noqa: E402
from hitops.io import tables  # noqa: E402
from hitops.io.metadata import read_metadata  # noqa: E402
from hitops.io.msv4.data_group import DataGroupWriter  # noqa: E402
from hitops.io.msv4.layout import read_layout  # noqa: E402
from hitops.io.msv4.rows import PartitionReader  # noqa: E402
from hitops.io.msv4.store import open_store  # noqa: E402
from hitops.testing import PairSpec, Troposphere  # noqa: E402
from msv4_sets import convert, file_digests  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")

SPEC = PairSpec(n_ant=4, n_time=300, n_scans=2, seed=11,
                troposphere=Troposphere(phase_offset_rad=2.1))
METHODS = ("pwc", "cfpt", "cwu")


@pytest.fixture(scope="module")
def converted(pair_store, tmp_path_factory):
    """(v2 reference, v2 target, v4 reference, v4 target) built and converted once."""
    root = tmp_path_factory.mktemp("v4cal")
    pair = pair_store.copy(SPEC, root)
    _flag_some(pair.ref_ms, pair.target_ms)
    return (str(pair.ref_ms), str(pair.target_ms), convert(pair.ref_ms, root / "ref.ps.zarr"),
            convert(pair.target_ms, root / "tgt.ps.zarr"))


def _flag_some(*sets) -> None:
    """Flags in both bands (3% of the samples), so that the outputs' flags carry the
    input's and the reference's gaps."""
    rng = np.random.default_rng(2)
    for ms in sets:
        flag = tables.read_columns(str(ms), ["FLAG"])["FLAG"]
        with tables.main_table(str(ms), writable=True) as t:
            t.putcol("FLAG", flag | (rng.random(flag.shape) < 0.03))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Simulated pairs of several groups, each (v2 ref, v2 target, v4 ref, v4 target): the
    wideband scene (two 230 GHz windows of 16 channels: two partitions, one ratio per
    channel) and the phaseref scene (a target and a calibrator in alternating scans: one
    partition holding two fields), 10 minutes each."""
    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    out = {}
    for name in ("wideband", "phaseref"):
        scene = load_scene_mapping(name)[0]
        scene["observation"]["duration"] = 600
        root = tmp_path_factory.mktemp(name)
        sets = simulate(scene, root)
        ref, tgt = sets["86"], sets["230"]
        _flag_some(ref, tgt)
        out[name] = (str(ref), str(tgt), str(convert(ref, root / "ref.ps.zarr")),
                     str(convert(tgt, root / "tgt.ps.zarr")))
    return out


@pytest.fixture
def copies(converted, tmp_path):
    """A private copy of all four sets."""
    out = []
    for path in converted:
        shutil.copytree(path, tmp_path / Path(path).name)
        out.append(str(tmp_path / Path(path).name))
    return out


def _v4_group(ps: str, group: str):
    """{(time, station, station): (data, flag)} of a data group, every partition."""
    layout = read_layout(open_store(ps))
    names = np.array(read_metadata(ps).antennas.names)
    rows = [c for p in layout.partitions
            for c in PartitionReader(layout, p.name, group).chunks(1 << 30)]
    time = np.concatenate([r.time for r in rows])
    a1 = names[np.concatenate([r.antenna1 for r in rows])]
    a2 = names[np.concatenate([r.antenna2 for r in rows])]
    order = np.lexsort((a2, a1, np.concatenate([r.data_desc_id for r in rows]), time))
    return (time[order], a1[order], a2[order], np.concatenate([r.data for r in rows])[order],
            np.concatenate([r.flag for r in rows])[order])


def _v2_columns(ms: str, column: str):
    cols = tables.read_columns(ms, ["TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", column,
                                    "FLAG"])
    names = np.array(read_metadata(ms).antennas.names)
    a1, a2 = names[cols["ANTENNA1"]], names[cols["ANTENNA2"]]
    order = np.lexsort((a2, a1, cols["DATA_DESC_ID"], cols["TIME"]))
    return cols["TIME"][order], a1[order], a2[order], cols[column][order], cols["FLAG"][order]


def assert_group_equals_column(ps: str, group: str, ms: str, column: str) -> None:
    t4, a14, a24, data4, flag4 = _v4_group(ps, group)
    t2, a12, a22, data2, flag2 = _v2_columns(ms, column)
    np.testing.assert_array_equal(t4, t2)
    np.testing.assert_array_equal(a14, a12)
    np.testing.assert_array_equal(a24, a22)
    np.testing.assert_array_equal(flag4, flag2, err_msg=f"{group} flags")
    assert flag2.any() and not flag2.all()      # a test of flags that can fail
    np.testing.assert_allclose(data4, data2, rtol=2e-7, atol=1e-6, err_msg=group)


def _input_digests(ps: str):
    """Digests of every file of the store but the root's and partitions' zarr.json (the
    new group's registration) and the new groups' arrays."""
    digests = file_digests(Path(ps))
    return {k: v for k, v in digests.items()
            if Path(k).name != "zarr.json" or len(Path(k).parts) > 2
            if not Path(k).parts[1:2] or not Path(k).parts[1].startswith(
                tuple(f"{v}_{m.upper()}" for v in ("VISIBILITY", "FLAG") for m in METHODS))}


@pytest.mark.parametrize("flags", [
    dict(tracker="count", chunk_rows=400),
    dict(tracker="antenna", offset_model="point", chunk_rows=700),
], ids=["count-chunks", "antenna-n0"])
def test_v4_run_writes_what_the_v2_run_writes(copies, flags, monkeypatch):
    ref2, tgt2, ref4, tgt4 = copies
    before = _input_digests(tgt4)
    ref_before = file_digests(Path(ref4))
    r2 = calibrate_flat(ref2, tgt2, method=",".join(METHODS), no_verdict=True, **flags)
    real, writers = DataGroupWriter.write_cells, set()

    def on_which_thread(self, *args):
        writers.add(threading.current_thread().name)
        return real(self, *args)

    monkeypatch.setattr(DataGroupWriter, "write_cells", on_which_thread)
    r4 = calibrate_flat(ref4, tgt4, method=",".join(METHODS), no_verdict=True, **flags)
    assert r4["chunks"] == r2["chunks"] > 1
    # a processing set's chunks are written on a thread of their own, beside the reads
    # (hitops/calibrate/chunk_io.py), and the output must not change for it: also the
    # antenna tracker's writing pass, which shifts the kept first pass (write_kept)
    assert writers == {"hitops-write_0"}
    assert r4["rows"] == r2["rows"]
    assert r4["wraps"] == r2["wraps"]
    assert r4["data_groups"]["cwu"] == {"data_group": "cwu", "partitions": ["target_0"]}
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")
    groups = json.loads((Path(tgt4) / "target_0" / "zarr.json").read_text())[
        "attributes"]["data_groups"]
    assert set(groups) == {"base", *METHODS}
    assert groups["pwc"]["weight"] == groups["base"]["weight"] == "WEIGHT"
    assert groups["pwc"]["flag"] == "FLAG_PWC" and groups["base"]["flag"] == "FLAG"
    assert _input_digests(tgt4) == before          # VISIBILITY, FLAG, ... untouched
    assert file_digests(Path(ref4)) == ref_before  # the reference only read


@pytest.mark.parametrize("scene, flags", [
    ("wideband", dict(offset_model="point", chunk_rows=600)),
    ("phaseref", dict(tracker="antenna", chunk_rows=500)),
])
def test_several_windows_and_fields_write_what_the_v2_run_writes(scenes, tmp_path, scene,
                                                                  flags):
    """Group by group: two windows in two partitions (per-channel ratios, the n0 step), or
    two fields in one partition (each field's time steps written without touching the
    other's)."""
    for path in scenes[scene]:
        shutil.copytree(path, tmp_path / Path(path).name)
    ref2, tgt2, ref4, tgt4 = (str(tmp_path / Path(p).name) for p in scenes[scene])
    before = _input_digests(tgt4)
    r2 = calibrate_flat(ref2, tgt2, method=",".join(METHODS), no_verdict=True, **flags)
    r4 = calibrate_flat(ref4, tgt4, method=",".join(METHODS), no_verdict=True, **flags)
    assert len(r4["groups"]) == len(r2["groups"]) == 2
    assert [g["chunks"] for g in r4["groups"]] == [g["chunks"] for g in r2["groups"]]
    assert min(g["chunks"] for g in r4["groups"]) > 1
    for method in METHODS:
        assert_group_equals_column(tgt4, method, tgt2, f"{method.upper()}_DATA")
    assert _input_digests(tgt4) == before


def test_a_taken_group_is_refused_and_overwrite_replaces_it(copies):
    _, _, ref4, tgt4 = copies
    calibrate_flat(ref4, tgt4, method="pwc", no_verdict=True)
    first = _v4_group(tgt4, "pwc")
    before = file_digests(Path(tgt4))
    with pytest.raises(OutputExistsError, match="PWC_DATA already exists"):
        calibrate_flat(ref4, tgt4, method="pwc", no_verdict=True)
    assert file_digests(Path(tgt4)) == before
    calibrate_flat(ref4, tgt4, method="pwc", no_verdict=True, overwrite=True, chunk_rows=500)
    again = _v4_group(tgt4, "pwc")
    np.testing.assert_array_equal(again[4], first[4])
    np.testing.assert_array_equal(again[3], first[3])
    with pytest.raises(InputError, match="names data group 'base'"):
        calibrate_flat(ref4, tgt4, method="pwc", output_column="BASE_DATA", overwrite=True,
                       no_verdict=True)


def test_a_run_stopped_in_a_chunk_leaves_the_store_as_it_was(copies, monkeypatch):
    _, _, ref4, tgt4 = copies
    before = file_digests(Path(tgt4))
    real, calls = DataGroupWriter.write_cells, []

    def fail_in_second_chunk(self, *args):
        calls.append(1)
        if len(calls) == 4:      # the second chunk's first write (two methods per chunk)
            raise KeyboardInterrupt
        return real(self, *args)

    monkeypatch.setattr(DataGroupWriter, "write_cells", fail_in_second_chunk)
    with pytest.raises(KeyboardInterrupt):
        calibrate_flat(ref4, tgt4, method="pwc,cfpt", no_verdict=True, chunk_rows=400)
    assert len(calls) == 4
    assert file_digests(Path(tgt4)) == before


@pytest.mark.parametrize("flag, value", [
    ("restore_flags", "before"), ("save_flags", "after")])
def test_modes_not_on_processing_sets_are_one_line(converted, flag, value):
    ref2, _, ref4, tgt4 = converted
    before = file_digests(Path(tgt4))
    with pytest.raises(InputError, match=f"with an MSv4 processing set \\({tgt4}\\)") as err:
        calibrate_flat(ref4, tgt4, method="pwc", **{flag: value})
    assert "\n" not in str(err.value)
    assert file_digests(Path(tgt4)) == before


def test_one_v2_band_and_one_v4_band(copies):
    """The backend is chosen per set: a v2 reference with a v4 target (and the other way
    round) gives the same outputs as the all-v2 run."""
    ref2, tgt2, ref4, tgt4 = copies
    calibrate_flat(ref2, tgt2, method="cfpt", no_verdict=True, chunk_rows=400)
    calibrate_flat(ref2, tgt4, method="cfpt", no_verdict=True, chunk_rows=400)
    assert_group_equals_column(tgt4, "cfpt", tgt2, "CFPT_DATA")
    calibrate_flat(ref4, tgt2, method="cfpt", output_column="CFPT4_DATA", no_verdict=True,
                   chunk_rows=400)
    np.testing.assert_array_equal(tables.read_columns(tgt2, ["CFPT4_DATA"])["CFPT4_DATA"],
                                  tables.read_columns(tgt2, ["CFPT_DATA"])["CFPT_DATA"])


def test_a_column_whose_data_group_is_missing_is_one_line(converted):
    """--target-column names a data group (CORRECTED_DATA -> 'corrected'): a store without it
    is refused before anything is written, naming the group and what the store answers to."""
    _, _, ref4, tgt4 = converted
    before = file_digests(Path(tgt4))
    with pytest.raises(ColumnError, match="has no data group 'corrected' \\(the column "
                                          "CORRECTED_DATA\\); check --target-column"):
        calibrate_flat(ref4, tgt4, method="pwc", target_column="CORRECTED_DATA")
    assert file_digests(Path(tgt4)) == before


def test_eht_m87_pair_writes_what_the_v2_run_writes(eht_imported, tmp_path):
    """Real data: the EHT 2017 M87 low and high bands after CASA importuvfits, converted by
    xradio; baselines come and go (a grid with cells missing, 7 of 8 stations in the low
    band), each (time, baseline) cell written where the v2 run writes its row."""
    sets = []
    for ms in eht_imported:
        copy = tmp_path / Path(ms).name
        shutil.copytree(ms, copy)
        sets.append(str(copy))
    ref4 = str(convert(sets[0], tmp_path / "lo.ps.zarr"))
    tgt4 = str(convert(sets[1], tmp_path / "hi.ps.zarr"))
    before = _input_digests(tgt4)
    flags = dict(method="cfpt,pwc", chunk_rows=2000, no_verdict=True)
    r2 = calibrate_flat(sets[0], sets[1], **flags)
    r4 = calibrate_flat(ref4, tgt4, **flags)
    assert r4["rows"] == r2["rows"] and r4["chunks"] == r2["chunks"] > 1
    for method in ("cfpt", "pwc"):
        assert_group_equals_column(tgt4, method, sets[1], f"{method.upper()}_DATA")
    assert _input_digests(tgt4) == before


def test_a_read_only_target_store_is_one_line(copies, tmp_path):
    """Behind a read-only bind mount (as tests/test_msv4_rows.py makes one): refused before
    the run starts (hitops/io/access.py's probe in each partition), exit 2 from the CLI."""
    import os
    import subprocess
    import sys

    _, _, ref4, tgt4 = copies
    view = tmp_path / "ro"
    view.mkdir()

    def mount(*args) -> bool:
        return subprocess.run(["mount", *args], capture_output=True).returncode == 0

    if os.geteuid() != 0 or not mount("--bind", str(Path(tgt4).parent), str(view)):
        pytest.skip("needs root to bind-mount read-only")
    try:
        if not mount("-o", "remount,bind,ro", str(view)):
            pytest.skip("read-only remount not permitted here")
        store = view / Path(tgt4).name
        before = file_digests(store)
        proc = subprocess.run([str(Path(sys.executable).with_name("hitops")), "calibrate", ref4,
                               str(store), "--method", "pwc"], capture_output=True, text=True,
                              timeout=300)
        out = proc.stdout + proc.stderr
        assert proc.returncode == 2 and "Traceback" not in out, out
        assert "cannot be written (target_0: Read-only file system)" in out, out
        assert file_digests(store) == before
    finally:
        subprocess.run(["umount", str(view)], capture_output=True)


def test_the_offset_step_reads_another_data_group(new_pair, tmp_path):
    """--offset-reference-column CORRECTED_DATA: on the processing set the 'corrected' group
    that xradio made of that column (a column of another data group than the band's), read
    beside the base group's data chunk by chunk; the n0 step's result equals the v2 run's."""
    from hitops.testing import add_column

    truth = new_pair(SPEC, tmp_path / "v2")
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase))
    _flag_some(truth.ref_ms, truth.target_ms)
    ref4 = str(convert(truth.ref_ms, tmp_path / "ref.ps.zarr"))
    tgt4 = str(convert(truth.target_ms, tmp_path / "tgt.ps.zarr"))
    assert "corrected" in {g.name for g in open_store(tgt4).partitions[0].data_groups}
    flags = dict(method="pwc,cwu", offset_reference_column="CORRECTED_DATA", chunk_rows=500,
                 no_verdict=True)
    r2 = calibrate_flat(str(truth.ref_ms), str(truth.target_ms), **flags)
    r4 = calibrate_flat(ref4, tgt4, **flags)
    assert r4["offset_step"]["series"] == r2["offset_step"]["series"]
    assert any(e["k"] != 0 for e in r4["offset_step"]["series"])
    for method in ("pwc", "cwu"):
        assert_group_equals_column(tgt4, method, str(truth.target_ms), f"{method.upper()}_DATA")
