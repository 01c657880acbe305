"""UVFITS from an MSv4 processing set's data group equals UVFITS from the v2 set's column.

Truth from outside: the same ``hitops calibrate --export-uvfits`` run on the Measurement
Sets v2 that xradio converted (v2 reader, hitops/io/uvfits_ms.py).  The file written from
the v4 run's ``pwc`` group must equal the file written from the v2 run's PWC_DATA: every
header card but the HISTORY lines naming the inputs, the random-group parameters exactly
(u, v, w, baseline, date, integration time), the visibilities to float32 rounding, the
weights exactly (their sign is the flag: the group's own FLAG_PWC must give the v2
run's FLAG, which carries the reference band's gaps, not the input's FLAG of ``base``),
and the AIPS AN/FQ/NX tables column by column; eht-imaging loads it.  Two windows of a
casatools.simulator layout become the same two IFs from either backend; two fields, a
missing data group and an existing file are one line each, the store as it was.

``--caltable`` (step 4 of the task): CASA's G Jones table of the antenna tracker written
from the processing set equals the v2 run's table, every column of it and of its
ANTENNA/FIELD/SPECTRAL_WINDOW/OBSERVATION/HISTORY subtables, keywords but MSName; CASA
applycal applies it to the v2 set and gives the pwc phases; the wideband scene's Fringe
Jones table (two windows) likewise.  Cost: about 25 s here (conversions, the runs,
one applycal; the pair's build is shared with tests/test_msv4_calibrate.py).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("xradio")
fits = pytest.importorskip("astropy.io.fits")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.errors import ColumnError, MeasurementSetError, OutputExistsError  # noqa: E402
from hitops.io import tables  # noqa: E402
from hitops.io.uvfits import export_uvfits  # noqa: E402
from msv4_sets import convert, file_digests, simulator_layout  # noqa: E402
from test_msv4_calibrate import SPEC, _flag_some  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")


def _vary_weights(ms) -> None:
    """WEIGHT per row and correlation drawn at random, so that the weights compared are not
    all one value."""
    rng = np.random.default_rng(4)
    weight = tables.read_columns(str(ms), ["WEIGHT"])["WEIGHT"]
    with tables.main_table(str(ms), writable=True) as t:
        t.putcol("WEIGHT", rng.uniform(0.5, 3.0, weight.shape).astype(np.float32))


@pytest.fixture(scope="module")
def runs(pair_store, tmp_path_factory):
    """{"v2"|"v4": (reference, target, exported file, report)} of the same calibrate run."""
    root = tmp_path_factory.mktemp("v4export")
    pair = pair_store.copy(SPEC, root)
    _flag_some(pair.ref_ms, pair.target_ms)
    _vary_weights(pair.target_ms)
    sets = {"v2": (str(pair.ref_ms), str(pair.target_ms)),
            "v4": (str(convert(pair.ref_ms, root / "ref.ps.zarr")),
                   str(convert(pair.target_ms, root / "tgt.ps.zarr")))}
    out = {}
    for kind, (ref, target) in sets.items():
        path = root / f"{kind}.uvfits"
        report = calibrate_flat(ref, target, method="pwc,cfpt", chunk_rows=400,
                                no_verdict=True, export_uvfits=str(path))
        out[kind] = (ref, target, path, report)
    return out


def _cards(hdu, drop=()):
    """The header's cards as text, without the HISTORY lines that name ``drop``."""
    return [c.image for c in hdu.header.cards
            if not (c.keyword == "HISTORY" and any(d in str(c.value) for d in drop))]


def assert_same_uvfits(v2_path, v4_path, names, stations_v4_lacks: int = 0) -> None:
    """The files equal as the module's docstring says; ``names``: input names whose HISTORY
    lines differ; ``stations_v4_lacks``: AN rows at the end of the v2 file's table (stations
    without rows) that the v4 file has not."""
    with fits.open(v2_path) as a, fits.open(v4_path) as b:
        assert len(a) == len(b) == 4
        assert _cards(a[0], names) == _cards(b[0], names)
        assert len(_cards(a[0])) == len(_cards(b[0]))
        ga, gb = a[0].data, b[0].data
        for k in range(len(ga.parnames)):
            np.testing.assert_array_equal(ga.par(k), gb.par(k), err_msg=ga.parnames[k])
        cube_a, cube_b = ga.data, gb.data        # (group, 1, 1, IF, chan, stokes, 3)
        np.testing.assert_allclose(cube_b[..., :2], cube_a[..., :2], rtol=2e-7, atol=1e-6)
        np.testing.assert_array_equal(cube_b[..., 2], cube_a[..., 2], err_msg="weights")
        for ha, hb in zip(a[1:], b[1:]):
            lacks = stations_v4_lacks if ha.name == "AIPS AN" else 0
            cards_a = [c for c in _cards(ha) if not (lacks and c.startswith("NAXIS2 "))]
            assert ha.name == hb.name and cards_a == [
                c for c in _cards(hb) if not (lacks and c.startswith("NAXIS2 "))]
            assert len(ha.data) - lacks == len(hb.data)
            for column in ha.columns.names:
                np.testing.assert_array_equal(ha.data[column][:len(hb.data)], hb.data[column],
                                              err_msg=f"{ha.name} {column}")


def test_the_v4_runs_export_equals_the_v2_runs(runs):
    v2, v4 = runs["v2"], runs["v4"]
    names = [Path(p).name for p in (*v2[:2], *v4[:2])]
    assert_same_uvfits(v2[2], v4[2], names)
    s2, s4 = v2[3]["export_uvfits"], v4[3]["export_uvfits"]
    assert s4["rows"] == s2["rows"] > 0 and s4["flagged"] == s2["flagged"]
    assert 0 < s4["flagged_fraction"] < 0.5
    with fits.open(v4[2]) as f:
        history = [str(c.value) for c in f[0].header.cards if c.keyword == "HISTORY"]
    assert "hitops: visibilities from data group pwc of tgt.ps.zarr" in history


def _rows_by_name(ms: str, column: str):
    """(keys, values, FLAG) of a set's rows in (TIME, station, station) order."""
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t, pt.table(f"{ms}::ANTENNA", ack=False) as ant:
        names = np.array(ant.getcol("NAME"))
        time, a1, a2 = t.getcol("TIME"), names[t.getcol("ANTENNA1")], names[t.getcol("ANTENNA2")]
        order = np.lexsort((a2, a1, time))
        return (time[order], a1[order], a2[order]), t.getcol(column)[order], \
            t.getcol("FLAG")[order]


def test_the_v4_export_converted_back_is_the_v2_runs_column(runs, tmp_path):
    """The road back to CASA and WSClean (docs/msv4.md, "Between the two worlds"): the v4
    run's UVFITS, converted by hitops.convert, is a Measurement Set whose DATA and FLAG
    are the v2 run's PWC_DATA and FLAG."""
    from hitops.io.convert import convert_cab

    back = tmp_path / "back.ms"
    convert_cab(str(runs["v4"][2]), str(back))
    keys4, data4, flag4 = _rows_by_name(str(back), "DATA")
    keys2, data2, flag2 = _rows_by_name(runs["v2"][1], "PWC_DATA")
    np.testing.assert_allclose(keys4[0], keys2[0], atol=1e-3)   # UVFITS dates: float
    for a, b in zip(keys4[1:], keys2[1:]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(flag4, flag2)
    assert flag2.any() and not flag2.all()
    ok = ~flag2
    np.testing.assert_allclose(data4[ok], data2[ok], rtol=2e-7, atol=1e-6)


def test_the_flags_are_the_output_groups_not_the_inputs(runs, tmp_path):
    """The pwc group's flags hold the reference band's gaps: the base group's flags (the
    input's FLAG) give other negative weights, so an export that took them would fail the
    comparison above.  The standalone export of ``base`` (DATA) equals the v2 DATA export
    of the set as converted, and leaves the store byte for byte as it was."""
    _, tgt4, v4_file, _ = runs["v4"]
    before = file_digests(Path(tgt4))
    base4 = export_uvfits(tgt4, tmp_path / "base.uvfits", "DATA")
    assert file_digests(Path(tgt4)) == before
    with fits.open(v4_file) as pwc, fits.open(tmp_path / "base.uvfits") as base:
        flagged_pwc = pwc[0].data.data[..., 2] < 0
        flagged_base = base[0].data.data[..., 2] < 0
    assert base4["flagged"] < flagged_pwc.sum() and (flagged_pwc & ~flagged_base).any()
    assert not (flagged_base & ~flagged_pwc).any()      # the input's flags are kept


def test_eht_imaging_loads_the_v4_export(runs):
    """eht-imaging drops the groups with no positive weight (every correlation flagged) and
    reads the rest: its RR visibilities are the file's unflagged RR values."""
    eh = pytest.importorskip("ehtim")
    v4_file = runs["v4"][2]
    obs = eh.obsdata.load_uvfits(str(v4_file), polrep="circ")
    with fits.open(v4_file) as f:
        an_names = [str(n).strip() for n in f["AIPS AN"].data["ANNAME"]]
        cube = np.asarray(f[0].data.data[:, 0, 0, 0, 0], np.float64)   # (group, stokes, 3)
    assert sorted(obs.tarr["site"]) == sorted(an_names)
    kept_groups = (cube[..., 2] > 0).any(axis=1)
    assert 0 < kept_groups.sum() < kept_groups.size       # some groups wholly flagged
    assert len(obs.data) == kept_groups.sum()
    rr = cube[kept_groups, 0]
    in_file = (rr[:, 0] + 1j * rr[:, 1])[rr[:, 2] > 0]
    read = obs.data["rrvis"][np.isfinite(obs.data["rrvis"])]
    # eht-imaging orders the rows its own way: the same values, compared sorted
    np.testing.assert_allclose(np.sort(read), np.sort(in_file), rtol=1e-6)


def test_the_export_cab_takes_a_processing_set(runs, tmp_path):
    """`stimela run` of cabs/interop.yml's hitops.export-uvfits with the store as its `ms`:
    the file equals export_uvfits' own of the same group, byte for byte."""
    import os
    import subprocess
    import sys

    tgt4 = runs["v4"][1]
    cabs = Path(__file__).resolve().parent.parent / "cabs"
    recipe = tmp_path / "export.yml"
    recipe.write_text(f"""_include:
  - {cabs / "hitops-pipeline.yml"}
  - {cabs / "interop.yml"}
export-v4:
  inputs:
    store: {{dtype: MS, required: true}}
  steps:
    export:
      cab: hitops.export-uvfits
      params: {{ms: =recipe.store, column: PWC_DATA, uvfits: {tmp_path / "cab.uvfits"}}}
""")
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ.get('PATH', '')}"}
    proc = subprocess.run([str(bin_dir / "stimela"), "run", str(recipe), f"store={tgt4}"],
                          cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    export_uvfits(tgt4, tmp_path / "direct.uvfits", "PWC_DATA")
    assert (tmp_path / "cab.uvfits").read_bytes() == (tmp_path / "direct.uvfits").read_bytes()


def test_the_eht_m87_pair_exports_the_same_file(eht_imported, tmp_path):
    """Real data: the EHT 2017 M87 pair after CASA importuvfits, converted by xradio.  Its
    rows average 4.4-10 s (INTTIM per row: the cells' EFFECTIVE_INTEGRATION_TIME), and
    the high band's ANTENNA table holds a station (SR) without rows, which the processing
    set does not carry: the v4 file's AN table is the v2 file's without that last row, all
    else equal."""
    sets = []
    for ms in eht_imported:
        shutil.copytree(ms, tmp_path / Path(ms).name)
        sets.append(str(tmp_path / Path(ms).name))
    stores = [str(convert(ms, tmp_path / f"{Path(ms).stem}.ps.zarr")) for ms in sets]
    flags = dict(method="pwc", no_verdict=True, chunk_rows=2000)
    calibrate_flat(*sets, export_uvfits=str(tmp_path / "v2.uvfits"), **flags)
    calibrate_flat(*stores, export_uvfits=str(tmp_path / "v4.uvfits"), **flags)
    with fits.open(tmp_path / "v2.uvfits") as a:
        an = a["AIPS AN"].data
        assert an["ANNAME"][-1] == "SR" and len(an) == 8
        assert not (a[0].data.par("BASELINE").astype(int) % 256 == 8).any()
        inttim = a[0].data.par("INTTIM")
        assert inttim.min() < 5 and inttim.max() == pytest.approx(10.0, abs=0.01)
    names = [Path(p).name for p in sets + stores]
    assert_same_uvfits(tmp_path / "v2.uvfits", tmp_path / "v4.uvfits", names,
                       stations_v4_lacks=1)


@pytest.fixture(scope="module")
def two_windows(tmp_path_factory):
    """A casatools.simulator layout (two windows of 16 channels, two correlations, two fields over
    three scans) and the same with every row moved to field 0, each as v2 and v4."""
    from casacore import tables as pt

    root = tmp_path_factory.mktemp("v4export-ifs")
    two_fields = simulator_layout(root / "fields.ms")
    one_field = simulator_layout(root / "field.ms")
    with pt.table(str(one_field), readonly=False, ack=False) as t:
        t.putcol("FIELD_ID", np.zeros(t.nrows(), np.int32))
    return {name: (str(ms), str(convert(ms, root / f"{name}.ps.zarr")))
            for name, ms in (("fields", two_fields), ("field", one_field))}


def test_windows_become_the_same_ifs_and_two_fields_are_one_line(two_windows, tmp_path):
    ms, ps = two_windows["field"]
    export_uvfits(ms, tmp_path / "v2.uvfits", "DATA")
    export_uvfits(ps, tmp_path / "v4.uvfits", "DATA")
    with fits.open(tmp_path / "v4.uvfits") as f:
        assert f[0].header["NAXIS5"] == 2 and f[0].header["NAXIS4"] == 16
    assert_same_uvfits(tmp_path / "v2.uvfits", tmp_path / "v4.uvfits",
                       [Path(ms).name, Path(ps).name])
    ms, ps = two_windows["fields"]
    before = file_digests(Path(ps))
    for path in (ms, ps):
        with pytest.raises(MeasurementSetError, match="holds 2 fields \\[0, 1\\]; UVFITS "
                                                      "export takes one") as err:
            export_uvfits(path, tmp_path / "x.uvfits", "DATA")
        assert "\n" not in str(err.value)
    assert not (tmp_path / "x.uvfits").exists() and file_digests(Path(ps)) == before


def test_a_missing_group_and_an_existing_file_are_one_line(runs, tmp_path):
    _, tgt4, v4_file, _ = runs["v4"]
    before = file_digests(Path(tgt4))
    with pytest.raises(ColumnError, match="has no data group 'corrected' \\(the column "
                                          "CORRECTED_DATA\\); name a data group") as err:
        export_uvfits(tgt4, tmp_path / "c.uvfits", "CORRECTED_DATA")
    assert "\n" not in str(err.value) and not (tmp_path / "c.uvfits").exists()
    with pytest.raises(OutputExistsError, match="exists; pass --overwrite"):
        export_uvfits(tgt4, v4_file, "PWC_DATA")
    assert file_digests(Path(tgt4)) == before


# ---------------------------------------------------------------- --caltable from a store

def _table_columns(path):
    """{(subtable, column): values} of a CASA table and the subtables a caltable carries
    (a column with no value in a row, e.g. OBSERVATION::LOG, is None), and its keywords
    but the subtables'."""
    from casacore import tables as pt

    out = {}
    for sub in ("", "ANTENNA", "FIELD", "SPECTRAL_WINDOW", "OBSERVATION", "HISTORY"):
        with pt.table(f"{path}/{sub}" if sub else str(path), ack=False) as t:
            out[(sub, "#rows")] = t.nrows()
            for column in t.colnames():
                try:
                    out[(sub, column)] = t.getcol(column)
                except RuntimeError:
                    out[(sub, column)] = None
            if not sub:
                out[("", "#keywords")] = {k: v for k, v in t.getkeywords().items()
                                          if not str(v).startswith("Table:")}
    return out


def assert_same_table(v2_table, v4_table, v4_store) -> None:
    """Every column of the main table and of its subtables equal; the keywords equal but
    MSName, which names the set each run was given."""
    a, b = _table_columns(v2_table), _table_columns(v4_table)
    assert a.keys() == b.keys()
    keywords_a, keywords_b = a.pop(("", "#keywords")), b.pop(("", "#keywords"))
    assert keywords_b.pop("MSName") == v4_store and keywords_a.pop("MSName")
    assert keywords_a == keywords_b
    for key, value in a.items():
        if isinstance(value, (list, dict)) or value is None:
            assert value == b[key], key
        else:
            np.testing.assert_array_equal(value, b[key], err_msg=str(key))
    assert a[("", "#rows")] > 0


def _applycal(ms, table) -> None:
    """CASA applycal in its own process (as tests/test_caltable_fpt.py runs it)."""
    import subprocess
    import sys

    code = ("import sys; from hitops.casa.runner import run_task; "
            "run_task('applycal', vis=sys.argv[1], gaintable=[sys.argv[2]], "
            "interp=['nearest'], applymode='calflag', calwt=[False], flagbackup=False)")
    subprocess.run([sys.executable, "-c", code, str(ms), str(table)], check=True,
                   capture_output=True, timeout=300)


def test_the_v4_runs_gain_table_equals_the_v2_runs_and_casa_applies_it(pair_store, tmp_path):
    """--tracker antenna --caltable: CASA's G Jones table written from the processing set
    (its subtables through hitops/io/msv4/casa_view.py) equals the v2 run's, every column;
    CASA applycal of it on the v2 set gives the pwc phases on every sample it keeps."""
    pair = pair_store.copy(SPEC, tmp_path)
    _flag_some(pair.ref_ms, pair.target_ms)
    ref4 = str(convert(pair.ref_ms, tmp_path / "ref.ps.zarr"))
    tgt4 = str(convert(pair.target_ms, tmp_path / "tgt.ps.zarr"))
    flags = dict(method="pwc", tracker="antenna", no_verdict=True, chunk_rows=700)
    before = file_digests(Path(tgt4))
    r4 = calibrate_flat(ref4, tgt4, caltable=str(tmp_path / "v4.G"), **flags)
    after_run = file_digests(Path(tgt4))
    # the table's view of the store only read it: the input's files are as they were
    # (the zarr.json files register the new pwc group)
    assert {k: v for k, v in after_run.items() if k in before and Path(k).name != "zarr.json"} \
        == {k: v for k, v in before.items() if Path(k).name != "zarr.json"}
    r2 = calibrate_flat(str(pair.ref_ms), str(pair.target_ms), caltable=str(tmp_path / "v2.G"),
                        **flags)
    assert r4["caltable"] == {**r2["caltable"], "path": str(tmp_path / "v4.G")}
    assert_same_table(tmp_path / "v2.G", tmp_path / "v4.G", tgt4)
    cols = tables.read_columns(str(pair.target_ms), ["PWC_DATA", "FLAG"])
    _applycal(pair.target_ms, tmp_path / "v4.G")
    after = tables.read_columns(str(pair.target_ms), ["CORRECTED_DATA", "FLAG"])
    ok = ~cols["FLAG"] & ~after["FLAG"]
    assert ok.mean() > 0.9
    turn = np.angle(after["CORRECTED_DATA"].astype(np.complex128)
                    * np.conj(cols["PWC_DATA"].astype(np.complex128)))[ok]
    assert np.max(np.abs(turn)) < 1e-5


def test_the_v4_runs_fringe_table_equals_the_v2_runs(tmp_path):
    """Two 230 GHz windows of 16 channels (the wideband scene, 10 minutes): the per-channel
    transfer's CASA Fringe Jones table (one SPECTRAL_WINDOW row per window, at its centre)
    from the processing set equals the v2 run's, every column."""
    from hitops.simulate import simulate
    from hitops.simulate.scene import load_scene_mapping

    scene = load_scene_mapping("wideband")[0]
    scene["observation"]["duration"] = 600
    sets = simulate(scene, tmp_path)
    ref4 = str(convert(sets["86"], tmp_path / "ref.ps.zarr"))
    tgt4 = str(convert(sets["230"], tmp_path / "tgt.ps.zarr"))
    flags = dict(method="pwc", tracker="antenna", no_verdict=True)
    calibrate_flat(ref4, tgt4, caltable=str(tmp_path / "v4.F"), **flags)
    calibrate_flat(str(sets["86"]), str(sets["230"]), caltable=str(tmp_path / "v2.F"), **flags)
    assert_same_table(tmp_path / "v2.F", tmp_path / "v4.F", tgt4)
    assert _table_columns(tmp_path / "v4.F")[("SPECTRAL_WINDOW", "#rows")] == 2
