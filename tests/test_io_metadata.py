"""The access layer (issue 36): a set's metadata read in one pass, and read once per run.

Opens are counted on python-casacore's own ``table`` (every open of hitops goes
through hitops/io/tables.py, which calls it), so a second read of a subtable, or
a reader that opens a subtable per window, shows as a count above one.
"""

from __future__ import annotations

import collections

import numpy as np
import pytest
from casacore import tables as pt

from hitops.io import metadata, tables
from hitops.testing import PairSpec


@pytest.fixture
def counted_opens(monkeypatch):
    """{path opened: count} of every casacore table open while the test runs."""
    counts = collections.Counter()
    real = pt.table

    def opened(name, *args, **kwargs):
        counts[str(name)] += 1
        return real(name, *args, **kwargs)

    monkeypatch.setattr(pt, "table", opened)
    return counts


def _pair(shared_pair):
    return shared_pair(PairSpec(n_ant=4, n_time=20, seed=3, corr_types=("RR", "RL", "LR", "LL")))


def test_metadata_is_the_sets_subtables(shared_pair):
    truth = _pair(shared_pair)
    ms = str(truth.target_ms)
    meta = metadata.read_metadata(ms)
    with pt.table(f"{ms}::ANTENNA", ack=False) as t:
        assert meta.antennas.names == tuple(t.getcol("NAME"))
        np.testing.assert_array_equal(meta.antennas.positions, t.getcol("POSITION"))
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        for i, window in enumerate(meta.windows):
            np.testing.assert_array_equal(window.chan_freq, t.getcell("CHAN_FREQ", i))
            assert window.ref_frequency == t.getcell("REF_FREQUENCY", i)
            assert window.num_chan == t.getcell("NUM_CHAN", i)
    with pt.table(f"{ms}::FIELD", ack=False) as t:
        np.testing.assert_array_equal(meta.fields.phase_dirs, t.getcol("PHASE_DIR")[:, 0, :])
    assert meta.window_of(0) == 0
    # RR RL LR LL and their receptors (R = 0, L = 1) as CORR_PRODUCT stores them
    assert meta.corr_types_of(0) == (5, 6, 7, 8)
    assert meta.polarizations[0].receptors == ((0, 0), (0, 1), (1, 0), (1, 1))
    assert not meta.has_groups()


def test_metadata_opens_each_subtable_once(shared_pair, counted_opens):
    ms = str(_pair(shared_pair).ref_ms)
    metadata.read_metadata(ms)
    subtables = ("ANTENNA", "FIELD", "SPECTRAL_WINDOW", "DATA_DESCRIPTION", "POLARIZATION")
    assert dict(counted_opens) == {f"{ms}::{name}": 1 for name in subtables}


def test_a_damaged_data_description_is_named(shared_pair):
    meta = metadata.read_metadata(str(_pair(shared_pair).ref_ms))
    with pytest.raises(metadata.MeasurementSetError, match="DATA_DESC_ID 3.*damaged"):
        meta.window_of(3)


def test_tables_read_and_write_through_one_seam(new_pair, tmp_path):
    truth = new_pair(PairSpec(n_ant=3, n_time=10), tmp_path)
    ms = str(truth.target_ms)
    assert tables.row_count(ms) == 3 * 10
    assert "DATA" in tables.column_names(ms)
    with tables.subtable(ms, "FIELD", writable=True) as t:
        t.putcell("NAME", 0, "renamed")
    assert tables.read_columns(f"{ms}::FIELD", ["NAME"])["NAME"][0] == "renamed"
    with pytest.raises(RuntimeError):   # read-only by default: casacore refuses the write
        with tables.subtable(ms, "FIELD") as t:
            t.putcell("NAME", 0, "again")


@pytest.mark.parametrize("tracker", ["count", "smooth"])
def test_a_calibrate_run_reads_each_subtable_once(new_pair, tmp_path, counted_opens, tracker):
    """build_plan reads each set's SetMetadata once and passes it down: groups, stations,
    the readers' one-group check and (smooth) the stations' elevations open no subtable
    again (the verdict, whose caller passes the run's metadata after the run skeleton's
    rewrite, is left out here)."""
    from hitops.calibrate import calibrate_flat

    truth = new_pair(PairSpec(n_ant=3, n_time=20), tmp_path)
    counted_opens.clear()   # the pair's build (the session's first) is not the run
    calibrate_flat(str(truth.ref_ms), str(truth.target_ms), method="pwc", no_verdict=True,
              overwrite=True, tracker=tracker)
    subtables = {name: n for name, n in counted_opens.items() if "::" in name}
    expected = {f"{ms}::{sub}": 1 for ms in (truth.ref_ms, truth.target_ms)
                for sub in ("ANTENNA", "FIELD", "SPECTRAL_WINDOW", "DATA_DESCRIPTION",
                            "POLARIZATION")}
    assert subtables == expected


def test_the_verdict_reads_no_subtable_given_the_runs_metadata(shared_pair, counted_opens):
    """calibrate/verdict.predict with the run's SetMetadata (RunPlan.ref_meta/tgt_meta) takes
    stations and correlations from it; without, it reads them itself."""
    from hitops.calibrate.verdict import predict

    truth = shared_pair(PairSpec(n_ant=3, n_time=120))
    ref, tgt = str(truth.ref_ms), str(truth.target_ms)
    metas = metadata.read_metadata(ref), metadata.read_metadata(tgt)
    counted_opens.clear()
    given = predict(ref, tgt, truth.ratio, ref_meta=metas[0], tgt_meta=metas[1])
    assert not [name for name in counted_opens if "::" in name]
    alone = predict(ref, tgt, truth.ratio)
    assert [name for name in counted_opens if "::" in name]
    assert given.closure == alone.closure and given.sampled == alone.sampled
