"""MSv4 processing sets: the format recognised, the metadata read (issue 37, first part).

Truth is the Measurement Set v2 each processing set was converted from by xradio
1.3: ``read_metadata`` of the processing set must give the v2 set's
:class:`SetMetadata` field by field, on a hitops synthetic pair, on a set laid out
by casatools.simulator (two windows, two fields) and on the EHT's M87 file after
CASA importuvfits.  Bad stores (foreign, half-written, another schema version)
are one ProcessingSetError line and stay byte for byte as they were.
Cost: about 6 s here (the simulator layout ~1 s, the EHT import shared with
tests/test_realdata.py, conversions ~0.5 s each).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("xradio")
import zarr  # noqa: E402

from hitops.errors import HitopsError, ProcessingSetError  # noqa: E402
from hitops.io import tables  # noqa: E402
from hitops.io.metadata import read_metadata  # noqa: E402
from hitops.io.msv4.store import is_processing_set, open_store  # noqa: E402
from hitops.testing import PairSpec  # noqa: E402
from hitops.testing.pairs import Signal  # noqa: E402
from msv4_sets import convert, file_digests, simulator_layout  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")

SPEC = PairSpec(n_ant=4, n_time=40, n_scans=2, signal=Signal(sigma_ref=0.2, sigma_target=0.2))


@pytest.fixture(scope="module")
def pair_sets(pair_store, tmp_path_factory):
    """(v2 reference set, its processing set)."""
    pair = pair_store.built(SPEC)
    return pair.ref_ms, convert(pair.ref_ms, tmp_path_factory.mktemp("ps") / "ref.ps.zarr")


@pytest.fixture(scope="module")
def simulator_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    ms = simulator_layout(root / "sim.ms")
    return ms, convert(ms, root / "sim.ps.zarr")


def assert_same_antennas(v2, v4):
    assert v4.names == v2.names and v4.stations == v2.stations and v4.mounts == v2.mounts
    np.testing.assert_array_equal(v4.positions, v2.positions)
    np.testing.assert_array_equal(v4.dish_diameters, v2.dish_diameters)


def assert_same_metadata(v2, v4, same_polarization_ids=True):
    """Field by field; ``same_polarization_ids`` False where the v2 set repeats a
    polarization setup (compared through each data description instead)."""
    assert_same_antennas(v2.antennas, v4.antennas)
    assert v4.fields.names == v2.fields.names
    np.testing.assert_array_equal(v4.fields.phase_dirs, v2.fields.phase_dirs)
    assert len(v4.windows) == len(v2.windows)
    for w2, w4 in zip(v2.windows, v4.windows):
        np.testing.assert_array_equal(w4.chan_freq, w2.chan_freq)
        np.testing.assert_array_equal(w4.chan_width, w2.chan_width)
        assert (w4.ref_frequency, w4.num_chan, w4.total_bandwidth, w4.net_sideband) == \
            (w2.ref_frequency, w2.num_chan, w2.total_bandwidth, w2.net_sideband)
    assert [d.window for d in v4.data_descriptions] == [d.window for d in v2.data_descriptions]
    for ddid, dd in enumerate(v2.data_descriptions):
        assert v4.corr_types_of(ddid) == v2.corr_types_of(ddid)
        assert (v4.polarizations[v4.data_descriptions[ddid].polarization].receptors
                == v2.polarizations[dd.polarization].receptors)
    if same_polarization_ids:
        assert v4.data_descriptions == v2.data_descriptions
        assert v4.polarizations == v2.polarizations


def test_pair_metadata_is_the_v2_sets(pair_sets):
    ms, ps = pair_sets
    assert is_processing_set(ps) and not is_processing_set(ms)
    v4 = read_metadata(ps)
    assert v4.ms == str(ps)
    assert_same_metadata(read_metadata(ms), v4)


def test_simulator_layout_windows_fields_and_receptors(simulator_sets):
    """Two windows of 16 channels, two fields: ids recovered from xradio's names."""
    ms, ps = simulator_sets
    v2, v4 = read_metadata(ms), read_metadata(ps)
    assert len(v2.windows) == 2 and v2.fields.names == ("M87", "3C273")
    # CASA's simulator writes one POLARIZATION row per window, both RR LL: a processing set
    # keeps the correlations of each partition, so the identical setups are one
    assert len(v2.polarizations) == 2 and len(v4.polarizations) == 1
    assert_same_metadata(v2, v4, same_polarization_ids=False)
    assert v4.has_groups() and v4.window_of(1) == 1


def test_eht_metadata_keeps_the_stations_with_rows(eht_imported, tmp_path):
    """The EHT's low band after importuvfits: NAME '1'..'8', codes in STATION; station 8
    (SR) has no row in this band, and a processing set keeps only antennas with rows."""
    lo_ms = eht_imported[0]
    v2, v4 = read_metadata(lo_ms), read_metadata(convert(lo_ms, tmp_path / "lo.ps.zarr"))
    cols = tables.read_columns(lo_ms, ["ANTENNA1", "ANTENNA2"])
    used = np.union1d(cols["ANTENNA1"], cols["ANTENNA2"])
    assert used.size < v2.antennas.n_ant                 # the case this test is about
    assert v4.antennas.names == tuple(v2.antennas.names[i] for i in used)
    assert v4.antennas.stations == tuple(v2.antennas.stations[i] for i in used)
    np.testing.assert_array_equal(v4.antennas.positions, v2.antennas.positions[used])
    assert v4.fields.names == v2.fields.names == ("M87",)
    np.testing.assert_array_equal(v4.windows[0].chan_freq, v2.windows[0].chan_freq)
    assert v4.polarizations == v2.polarizations          # RR RL LR LL and their receptors


# ------------------------------------------------------------------ bad stores


def _copy(ps, tmp_path):
    out = tmp_path / "copy.ps.zarr"
    shutil.copytree(ps, out)
    return out


def _edit_json(path, edit):
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _refused(path, *words):
    before = file_digests(path)
    with pytest.raises(ProcessingSetError) as err:
        read_metadata(path)
    message = str(err.value)
    assert isinstance(err.value, HitopsError) and "\n" not in message and str(path) in message
    for word in words:
        assert word in message
    assert file_digests(path) == before
    return message


def test_foreign_zarr_store(tmp_path):
    store = tmp_path / "foreign.zarr"
    zarr.open_group(store, mode="w").create_array("x", shape=(3,), dtype="f8")
    _refused(store, "not an MSv4 processing set")
    v2_store = tmp_path / "old.zarr"
    zarr.open_group(v2_store, mode="w", zarr_format=2).create_array("x", shape=(3,), dtype="f8")
    _refused(v2_store, "zarr v2")


def test_other_schema_version(pair_sets, tmp_path):
    ps = _copy(pair_sets[1], tmp_path)
    partition = open_store(ps).partitions[0].name
    _edit_json(ps / partition / "zarr.json",
               lambda d: d["attributes"].__setitem__("schema_version", "3.1.0"))
    _refused(ps, partition, "schema_version '3.1.0'", "4.0")


def test_conversion_that_did_not_finish(pair_sets, tmp_path):
    """xradio writes the root's type last: partitions under an untyped root are half-written."""
    ps = _copy(pair_sets[1], tmp_path)
    _edit_json(ps / "zarr.json", lambda d: d["attributes"].pop("type"))
    _refused(ps, "did not finish")


def test_partition_without_consolidated_metadata(pair_sets, tmp_path):
    ps = _copy(pair_sets[1], tmp_path)
    partition = open_store(ps).partitions[0].name
    _edit_json(ps / partition / "zarr.json", lambda d: d.pop("consolidated_metadata"))
    _refused(ps, partition, "did not finish")


def test_partition_missing_from_the_root_metadata(pair_sets, tmp_path):
    ps = _copy(pair_sets[1], tmp_path)
    partition = open_store(ps).partitions[0].name
    shutil.copytree(ps / partition, ps / "late_7")
    _refused(ps, "late_7", "not in the store's consolidated metadata")


def test_calibrate_on_a_half_written_store_says_so(pair_sets, tmp_path):
    """``hitops calibrate`` takes processing sets (tests/test_msv4_calibrate.py); a store whose
    conversion did not finish is one line naming it and the way on: exit 2, no traceback,
    the store unchanged."""
    import subprocess
    import sys
    from pathlib import Path

    ps = _copy(pair_sets[1], tmp_path)
    _edit_json(ps / "zarr.json", lambda d: d["attributes"].pop("type"))
    before = file_digests(ps)
    proc = subprocess.run([str(Path(sys.executable).with_name("hitops")), "calibrate",
                           str(pair_sets[0]), str(ps)], capture_output=True, text=True,
                          timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out
    assert "Traceback" not in out and "conversion did not finish" in out, out
    assert str(ps) in out
    assert file_digests(ps) == before


def test_without_the_msv4_extra(pair_sets, monkeypatch):
    """zarr not importable (the extra not installed): one line saying how to install it."""
    monkeypatch.setitem(__import__("sys").modules, "zarr", None)
    with pytest.raises(ProcessingSetError, match=r"needs the msv4 extra \(pip install"):
        read_metadata(pair_sets[1])
