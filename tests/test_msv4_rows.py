"""MSv4 partitions read as rows and a data group written whole (issue 37, first part).

Reader truth: the Measurement Set v2 each processing set was converted from (the
EHT M87 low band after importuvfits, which lacks rows on some baselines and
times; a casatools.simulator layout with two windows, two fields, random DATA and
flags).  Writer truth: values written chunk by chunk, read back with xarray
(``open_datatree``, as a user of the processing set reads it), and the input's
files byte for byte as before.  Cost: about 8 s here.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

pytest.importorskip("xradio")
import xarray as xr  # noqa: E402
import zarr  # noqa: E402

from hitops.errors import OutputExistsError, ProcessingSetError  # noqa: E402
from hitops.io import tables  # noqa: E402
from hitops.io.metadata import read_metadata  # noqa: E402
from hitops.io.msv4.data_group import DataGroupWriter  # noqa: E402
from hitops.io.msv4.layout import read_layout  # noqa: E402
from hitops.io.msv4.rows import PartitionReader  # noqa: E402
from hitops.io.msv4.store import open_store  # noqa: E402
from msv4_sets import convert, file_digests, simulator_layout  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")
COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "FIELD_ID", "SCAN_NUMBER", "DATA",
           "FLAG", "UVW"]


@pytest.fixture(scope="module")
def eht_sets(eht_imported, tmp_path_factory):
    lo_ms = eht_imported[0]
    return lo_ms, convert(lo_ms, tmp_path_factory.mktemp("eht-ps") / "lo.ps.zarr")


@pytest.fixture(scope="module")
def simulator_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim-rows")
    ms = simulator_layout(root / "sim.ms", seed=9)
    return ms, convert(ms, root / "sim.ps.zarr")


def _v2_rows(ms, ddid, names):
    """The v2 set's rows of ``ddid`` by (TIME, ANTENNA1 name, ANTENNA2 name)."""
    cols = tables.read_columns(ms, COLUMNS)
    keep = cols["DATA_DESC_ID"] == ddid
    cols = {k: v[keep] for k, v in cols.items()}
    order = np.lexsort((names[cols["ANTENNA2"]], names[cols["ANTENNA1"]], cols["TIME"]))
    return {k: v[order] for k, v in cols.items()}


def _v4_rows(chunks, names):
    keys = ("time", "antenna1", "antenna2", "data_desc_id", "field_id", "scan_number", "data",
            "flag", "uvw")
    rows = {k: np.concatenate([getattr(c, k) for c in chunks]) for k in keys}
    order = np.lexsort((names[rows["antenna2"]], names[rows["antenna1"]], rows["time"]))
    return {k: v[order] for k, v in rows.items()}


def _assert_rows_equal(ms, ps, partition_chunks):
    """Every partition's rows equal the v2 rows of its data description, value for value."""
    v2_names = np.array(read_metadata(ms).antennas.names)
    v4_names = np.array(read_metadata(ps).antennas.names)
    for place, chunks in partition_chunks:
        v2, v4 = _v2_rows(ms, place.data_desc_id, v2_names), _v4_rows(chunks, v4_names)
        assert v4["time"].size == v2["TIME"].size > 0
        np.testing.assert_array_equal(v4["time"], v2["TIME"])          # MSv2 seconds, exactly
        np.testing.assert_array_equal(v4_names[v4["antenna1"]], v2_names[v2["ANTENNA1"]])
        np.testing.assert_array_equal(v4_names[v4["antenna2"]], v2_names[v2["ANTENNA2"]])
        for key in ("data_desc_id", "field_id", "scan_number", "data", "flag", "uvw"):
            np.testing.assert_array_equal(v4[key], v2[key.upper()], err_msg=key)


def test_eht_rows_are_the_v2_rows(eht_sets):
    """Missing (baseline, time) cells are no rows: the row count is the v2 set's."""
    ms, ps = eht_sets
    layout = read_layout(open_store(ps))
    reader = PartitionReader(layout, layout.partitions[0].name)
    assert reader.n_time * reader.n_baseline > tables.row_count(ms)   # cells without rows
    chunks = list(reader.chunks(500, variables=("DATA", "FLAG", "UVW")))
    assert len(chunks) > 3
    _assert_rows_equal(ms, ps, [(layout.partitions[0], chunks)])


def test_simulator_rows_windows_fields_scans(simulator_sets):
    ms, ps = simulator_sets
    layout = read_layout(open_store(ps))
    assert len(layout.partitions) == 2
    pairs = [(p, list(PartitionReader(layout, p.name).chunks(
        100, variables=("DATA", "FLAG", "UVW")))) for p in layout.partitions]
    _assert_rows_equal(ms, ps, pairs)
    assert {int(f) for _, c in pairs for x in c for f in x.field_id} == {0, 1}


def test_time_range_and_only_the_variables_asked(eht_sets, tmp_path):
    """A time range gives the v2 rows of that range; a read of FLAG alone never touches
    VISIBILITY (its chunk files removed from a copy: the read still succeeds)."""
    ms, ps = eht_sets
    copy = tmp_path / "copy.ps.zarr"
    shutil.copytree(ps, copy)
    layout = read_layout(open_store(copy))
    name = layout.partitions[0].name
    shutil.rmtree(copy / name / "VISIBILITY" / "c")
    reader = PartitionReader(layout, name)
    times = np.unique(tables.read_columns(ms, ["TIME"])["TIME"])
    t_lo, t_hi = times[10], times[40]
    rows = [c for c in reader.chunks(200, variables=("FLAG",), t_lo=t_lo, t_hi=t_hi)]
    got = np.concatenate([c.time for c in rows])
    v2_time = tables.read_columns(ms, ["TIME"])["TIME"]
    assert got.size == np.count_nonzero((v2_time >= t_lo) & (v2_time < t_hi))
    assert got.min() == t_lo and got.max() < t_hi
    assert all(c.data is None and c.flag.shape == (c.n_row, 1, 4) for c in rows)
    with pytest.raises(ProcessingSetError, match="cannot read"):
        reader.read((0, 1), variables=("MODEL",))


# ------------------------------------------------------------------ the data group writer


def _writable(ps, tmp_path):
    out = tmp_path / "w.ps.zarr"
    shutil.copytree(ps, out)
    return out


def _write_group(ps, name, overwrite=False, fail_after=None, rows_per_chunk=600):
    """Data group ``name``: conj(data) * 2 and flags where ANTENNA1 is 0, chunk by chunk
    (stopped by a KeyboardInterrupt at chunk ``fail_after`` of the first partition)."""
    layout = read_layout(open_store(ps))
    for place in layout.partitions:
        reader = PartitionReader(layout, place.name)
        with DataGroupWriter(str(ps), place.name, name, overwrite=overwrite,
                             time_chunk=reader.time_step(rows_per_chunk)) as writer:
            for k, rows in enumerate(reader.chunks(rows_per_chunk)):
                if fail_after is not None and k == fail_after:
                    raise KeyboardInterrupt("stopped")
                writer.write(rows, np.conj(rows.data) * 2,
                             rows.flag | (rows.antenna1 == 0)[:, None, None])


def test_written_group_read_back_with_xarray(simulator_sets, tmp_path):
    ms, ps = simulator_sets
    ps = _writable(ps, tmp_path)
    inputs = file_digests(ps, skip={"zarr.json", "VISIBILITY_PWC", "FLAG_PWC"})
    _write_group(ps, "pwc", rows_per_chunk=120)
    assert file_digests(ps, skip={"zarr.json", "VISIBILITY_PWC", "FLAG_PWC"}) == inputs
    tree = xr.open_datatree(ps, engine="zarr")
    for partition in open_store(ps).partitions:
        ds = tree[partition.name].ds
        group = ds.attrs["data_groups"]["pwc"]
        assert (group["correlated_data"], group["flag"], group["weight"], group["uvw"]) == \
            ("VISIBILITY_PWC", "FLAG_PWC", "WEIGHT", "UVW")
        present = np.isfinite(ds.EFFECTIVE_INTEGRATION_TIME.values)
        np.testing.assert_array_equal(ds.VISIBILITY_PWC.values[present],
                                      np.conj(ds.VISIBILITY.values[present]) * 2)
        ant0 = (ds.baseline_antenna1_name.values == tree[partition.name]["antenna_xds"]
                .ds.antenna_name.values[0])
        expect_flag = ds.FLAG.values | ant0[None, :, None, None]
        np.testing.assert_array_equal(ds.FLAG_PWC.values, expect_flag)
    # the new arrays are stored in the chunks the writer wrote (whole zarr chunks per write)
    group = zarr.open_group(str(ps), path=partition.name, mode="r")
    assert group["VISIBILITY_PWC"].chunks[0] == 120 // ds.sizes["baseline_id"] < ds.sizes["time"]
    assert group["VISIBILITY"].chunks[0] == ds.sizes["time"]
    # and through hitops's own reader, as the group's rows
    layout = read_layout(open_store(ps))
    place = layout.partitions[1]
    base = list(PartitionReader(layout, place.name).chunks(10**6))[0]
    mine = list(PartitionReader(layout, place.name, data_group="pwc").chunks(10**6))[0]
    np.testing.assert_array_equal(mine.data, np.conj(base.data) * 2)


def test_cells_without_rows_are_nan_and_flagged(eht_sets, tmp_path):
    ms, ps = eht_sets
    ps = _writable(ps, tmp_path)
    _write_group(ps, "pwc")
    ds = xr.open_datatree(ps, engine="zarr")[open_store(ps).partitions[0].name].ds
    absent = ~np.isfinite(ds.EFFECTIVE_INTEGRATION_TIME.values)
    assert absent.any()
    assert np.isnan(ds.VISIBILITY_PWC.values[absent]).all() and ds.FLAG_PWC.values[absent].all()


def test_existing_group_refused_then_overwritten(simulator_sets, tmp_path):
    ms, ps = simulator_sets
    ps = _writable(ps, tmp_path)
    name = open_store(ps).partitions[0].name
    before = file_digests(ps)
    with pytest.raises(OutputExistsError, match="already has data group 'corrected'"):
        DataGroupWriter(str(ps), name, "corrected")
    assert file_digests(ps) == before
    _write_group(ps, "pwc")
    with pytest.raises(OutputExistsError, match="--overwrite"):
        DataGroupWriter(str(ps), name, "pwc")
    _write_group(ps, "pwc", overwrite=True)
    assert [g.name for g in open_store(ps).partition(name).data_groups].count("pwc") == 1


def test_interrupted_write_leaves_the_store_as_it_was(simulator_sets, tmp_path):
    ms, ps = simulator_sets
    ps = _writable(ps, tmp_path)
    before = file_digests(ps)
    with pytest.raises(KeyboardInterrupt):
        _write_group(ps, "pwc", fail_after=1, rows_per_chunk=100)
    assert file_digests(ps) == before
    # a killed run (staged, never committed): no reader sees the group, the next run cleans up
    name = open_store(ps).partitions[0].name
    DataGroupWriter(str(ps), name, "pwc").stage()
    assert "pwc" not in xr.open_datatree(ps, engine="zarr")[name].ds.attrs["data_groups"]
    assert "pwc" not in [g.name for g in open_store(ps).partition(name).data_groups]
    _write_group(ps, "pwc")
    assert "pwc" in xr.open_datatree(ps, engine="zarr")[name].ds.attrs["data_groups"]


def test_foreign_array_and_bad_names_refused(simulator_sets, tmp_path):
    ms, ps = simulator_sets
    ps = _writable(ps, tmp_path)
    name = open_store(ps).partitions[0].name
    with pytest.raises(ProcessingSetError, match="lower-case"):
        DataGroupWriter(str(ps), name, "PWC data")
    shutil.copytree(ps / name / "WEIGHT", ps / name / "VISIBILITY_CWU")
    with pytest.raises(ProcessingSetError, match="VISIBILITY_CWU that no data group names"):
        DataGroupWriter(str(ps), name, "cwu")


def _mount(*args) -> bool:
    import subprocess

    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


def test_read_only_store_refused(simulator_sets, tmp_path):
    """Behind a read-only bind mount (as tests/test_cli_boundary.py makes one): one line."""
    import os
    import subprocess

    ms, ps = simulator_sets
    source = _writable(ps, tmp_path)
    view = tmp_path / "ro"
    view.mkdir()
    if os.geteuid() != 0 or not _mount("--bind", str(source.parent), str(view)):
        pytest.skip("needs root to bind-mount read-only")
    try:
        if not _mount("-o", "remount,bind,ro", str(view)):
            pytest.skip("read-only remount not permitted here")
        store = view / source.name
        before = file_digests(store)
        with pytest.raises(ProcessingSetError, match="is not writable .*writable copy"):
            DataGroupWriter(str(store), open_store(store).partitions[0].name, "pwc")
        assert file_digests(store) == before
    finally:
        subprocess.run(["umount", str(view)], capture_output=True)


def test_full_steps_read_without_presence_give_the_same_rows(simulator_sets):
    """``every_cell`` (the group's row counts say the steps are full) skips the presence
    read and builds the rows' cells by arithmetic: the rows are the ones read through the
    presence array, value for value; and the run-length lookup of field and scan names
    gives each step's FIELD_ID and SCAN_NUMBER as a lookup per step does."""
    from hitops.io.msv4.group_rows import open_partition_groups
    from hitops.io.msv4.rows import _per_time

    _, ps = simulator_sets
    layout = read_layout(open_store(ps))
    for place in layout.partitions:
        reader = PartitionReader(layout, place.name)
        present = reader.present(0, reader.n_time)
        full = present.all(axis=1)
        # the first two consecutive full steps (several steps: the cells' order is tested)
        start = int(np.flatnonzero(full[:-1] & full[1:])[0])
        span = (start, start + 2)
        a = reader.read(span, ("DATA", "FLAG", "UVW"))
        b = reader.read(span, ("DATA", "FLAG", "UVW"), every_cell=True)
        for key, value in vars(a).items():
            np.testing.assert_array_equal(getattr(b, key), value, err_msg=key)
        known = {n: i for i, n in enumerate(layout.fields.v4_names)}
        names = np.asarray(zarr.open_group(ps, mode="r")[place.name]["field_name"][...])
        np.testing.assert_array_equal(reader.field_ids, [known[str(n)] for n in names])
    # names that come back after another run (A A B A C): one number per step still
    steps = np.array(["A", "A", "B", "A", "C", "C"])
    np.testing.assert_array_equal(_per_time(steps, {"A": 0, "B": 7, "C": 3}.get),
                                  [0, 0, 7, 0, 3, 3])
    # a group whose steps are not all full (the simulator's flagged-out cells or fields
    # sharing a partition) keeps the per-step search; a full one the arithmetic
    for source in open_partition_groups(ps, ["DATA"]).values():
        positions = np.arange(source.n_rows, dtype=np.int64)
        times, baselines = source.cells(positions)
        reader = source.reader(source.group)
        present = reader.present(0, reader.n_time)
        assert present[times, baselines].all()
        assert np.unique(times * reader.n_baseline + baselines).size == source.n_rows


def test_one_field_partitions_take_their_field_without_reading_names(simulator_sets,
                                                                     tmp_path):
    """A partition whose field_and_source dataset lists one field gives every step that
    field's FIELD_ID without reading the per-step names; one that lists several reads
    them.  Both agree with the names xradio stored, in the default scheme (fields share
    partitions) and partitioned by field."""
    from xradio.measurement_set import convert_msv2_to_processing_set

    ms, shared = simulator_sets
    by_field = tmp_path / "by-field.ps.zarr"
    convert_msv2_to_processing_set(str(ms), str(by_field), partition_scheme=["FIELD_ID"])
    kinds = set()
    for ps in (str(shared), str(by_field)):
        layout = read_layout(open_store(ps))
        known = {n: i for i, n in enumerate(layout.fields.v4_names)}
        for place in layout.partitions:
            reader = PartitionReader(layout, place.name)
            names = np.asarray(zarr.open_group(ps, mode="r")[place.name]["field_name"][...])
            np.testing.assert_array_equal(reader.field_ids, [known[str(n)] for n in names])
            kinds.add(len(place.field_v4_names) == 1)
            # the one-field shortcut opened no field_name array
            assert ("field_name" in reader._arrays) == (len(place.field_v4_names) > 1)
    assert kinds == {True, False}


def test_time_ordered_blocks_merge_as_the_sort_merges():
    """The index pass keeps a time-ordered band's blocks' distinct times and joins them
    once (the one time a block boundary cuts counted once, its rows added), and a block
    after the known times (storage order's new times) is appended: both give the sorting
    merge's result."""
    from hitops.calibrate.band_index import _merge_time_counts, _OrderedTimes

    rng = np.random.default_rng(4)
    times = np.sort(rng.integers(0, 400, 5000)).astype(np.float64)
    expected, expected_counts = np.unique(times, return_counts=True)
    ordered = _OrderedTimes()
    known, counts = np.zeros(0), np.zeros(0, np.int64)
    for a in range(0, times.size, 613):    # blocks cutting times in two
        values, n = np.unique(times[a:a + 613], return_counts=True)
        ordered.add(values, n)
        known, counts = _merge_time_counts(known, counts, values, n.astype(np.int64))
    for got, got_counts in (ordered.join(), (known, counts)):
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(got_counts, expected_counts)
        assert got_counts.dtype == np.int64


@pytest.mark.parametrize("which", ["eht", "simulator"])
def test_grid_index_is_the_row_pass_index(which, eht_sets, simulator_sets, monkeypatch):
    """A processing-set group read in several blocks is indexed from its partition's grid
    (hitops/calibrate/band_index.py ``_index_from_grid``): every summary and each row's
    pair key equal, value and type, what the row pass over TIME, ANTENNA1/2, SCAN_NUMBER
    and INTERVAL finds.  The EHT set lacks rows on some baselines and times; the simulator's
    has two windows and two fields sharing a partition, and flagged-out cells: a grid
    counted as full, or steps of the other field taken, would fail here."""
    from hitops.calibrate import band_index
    from hitops.calibrate.band_index import INDEX_COLUMNS, BandSource, index_bands
    from hitops.io.msv4.group_rows import open_partition_groups

    _, ps = eht_sets if which == "eht" else simulator_sets
    n_ant = len(read_layout(open_store(ps)).antennas.v4_names)
    groups = open_partition_groups(str(ps), ["DATA"])
    sources = [BandSource(ms=str(ps), ds=g, n_row=g.n_rows, n_ant=n_ant, key=key)
               for key, g in sorted(groups.items())]
    # several blocks per group, cutting time steps (a prime: no baseline count divides it)
    block_rows = 23
    assert min(s.n_row for s in sources) > 3 * block_rows
    taken = []
    from_grid = band_index._index_from_grid
    monkeypatch.setattr(band_index, "_index_from_grid",
                        lambda band, rows: taken.append(from_grid(band, rows)) or taken[-1])
    fast = index_bands(sources, [INDEX_COLUMNS] * len(sources), block_rows)
    assert taken == [True] * len(sources)
    monkeypatch.setattr(band_index, "_index_from_grid", lambda band, rows: False)
    slow = index_bands(sources, [INDEX_COLUMNS] * len(sources), block_rows)
    for got, expected in zip(fast, slow):
        for name, value in vars(expected).items():
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(getattr(got, name), value, err_msg=name)
                assert getattr(got, name).dtype == value.dtype, name
            else:
                assert getattr(got, name) == value, name
