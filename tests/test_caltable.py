"""hitops.io.caltable: a phase-only G Jones table that CASA applycal applies as intended.

The reference is CASA itself: the table's layout is compared with one CASA
gaincal wrote on the same set, and CASA applycal (the real task) applies a
table of known per-antenna phases; CORRECTED_DATA must equal
DATA * exp(-i (phi_p - phi_q)) on every unflagged sample, and flagged
solutions must flag exactly the samples they touch.
"""

from __future__ import annotations

import numpy as np
import pytest

from hitops.testing import PairSpec
from hitops.errors import InputError, OutputExistsError
from hitops.io.caltable import write_gain_table

#: (receptor of antenna p, receptor of antenna q) of each correlation
RECEPTORS = {"RR": (0, 0), "RL": (0, 1), "LR": (1, 0), "LL": (1, 1)}


def _times(ms):
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        return np.unique(t.getcol("TIME"))


def _applycal(ms, table, interp="linear"):
    from hitops.casa.runner import run_task

    run_task("applycal", vis=str(ms), gaintable=[str(table)], interp=[interp],
             applymode="calflag", calwt=[False], flagbackup=False)


@pytest.fixture()
def pair(new_pair):
    # two scans, all four correlations, baselines stored in both antenna orders
    return new_pair(PairSpec(n_ant=4, n_time=40, dt=2.0, n_scans=2,
                             corr_types=("RR", "RL", "LR", "LL")))


def test_layout_is_casa_gaincal_layout(pair, tmp_path):
    from casacore import tables as pt

    from hitops.casa.runner import run_task

    ms = pair.target_ms
    times = _times(ms)
    phase = np.zeros((times.size, 4, 2))
    ours = write_gain_table(tmp_path / "fpt.G", ms, times, phase, None, ["RR", "LL"], refant=0)
    run_task("gaincal", vis=str(ms), caltable=str(tmp_path / "casa.G"), solint="int",
             refant="AP", calmode="p", gaintype="G", minsnr=0.0, minblperant=2)
    with pt.table(ours, ack=False) as a, pt.table(str(tmp_path / "casa.G"), ack=False) as b:
        assert a.info() == b.info()                       # type Calibration, subType G Jones
        ka, kb = a.getkeywords(), b.getkeywords()
        assert set(ka) == set(kb)
        for key in ("ParType", "VisCal", "PolBasis", "MSName"):
            assert ka[key] == kb[key]
        assert a.colnames() == b.colnames()
        for col in a.colnames():
            da, db = a.getcoldesc(col), b.getcoldesc(col)
            assert da["valueType"] == db["valueType"] and da.get("ndim") == db.get("ndim"), col
            assert da.get("keywords") == db.get("keywords"), col
        assert a.nrows() == b.nrows() == times.size * 4
        for col in ("TIME", "ANTENNA1", "ANTENNA2", "SPECTRAL_WINDOW_ID", "FIELD_ID",
                    "SCAN_NUMBER", "OBSERVATION_ID", "INTERVAL"):
            np.testing.assert_array_equal(a.getcol(col), b.getcol(col), err_msg=col)
        assert a.getcol("CPARAM").shape == b.getcol("CPARAM").shape == (times.size * 4, 1, 2)
        for sub in ("ANTENNA", "FIELD", "SPECTRAL_WINDOW", "OBSERVATION", "HISTORY"):
            with pt.table(f"{ours}/{sub}", ack=False) as sa, \
                    pt.table(str(tmp_path / "casa.G" / sub), ack=False) as sb:
                assert sa.colnames() == sb.colnames() and sa.nrows() == sb.nrows(), sub


def test_applycal_removes_the_antenna_phases_and_flags_what_it_should(pair, tmp_path):
    from casacore import tables as pt

    ms = pair.target_ms
    times = _times(ms)
    rng = np.random.default_rng(3)
    phase = rng.uniform(-np.pi, np.pi, (times.size, 4, 2))
    valid = np.ones(phase.shape, bool)
    valid[10, 2, 0] = False            # antenna 2, R, one time
    valid[11:14, 1, 1] = False         # antenna 1, L, three times
    valid[30, 3, :] = False            # antenna 3, both receptors
    table = write_gain_table(tmp_path / "fpt.G", ms, times, phase, valid, ["RR", "LL"], refant=0)
    with pt.table(str(ms), ack=False) as t:
        flag_before = t.getcol("FLAG")[:, 0, :]
    _applycal(ms, table)
    with pt.table(str(ms), ack=False) as t:
        data = t.getcol("DATA")[:, 0, :].astype(np.complex128)
        corrected = t.getcol("CORRECTED_DATA")[:, 0, :].astype(np.complex128)
        flag = t.getcol("FLAG")[:, 0, :]
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        it = np.searchsorted(times, t.getcol("TIME"))
        corrs = ["RR", "RL", "LR", "LL"]
    expected = np.empty_like(data)
    touched = np.zeros(flag.shape, bool)
    for k, c in enumerate(corrs):
        rp, rq = RECEPTORS[c]
        expected[:, k] = data[:, k] * np.exp(-1j * (phase[it, a1, rp] - phase[it, a2, rq]))
        touched[:, k] = ~valid[it, a1, rp] | ~valid[it, a2, rq]
    # flags: exactly the samples a flagged solution touches (and those flagged before)
    np.testing.assert_array_equal(flag, flag_before | touched)
    assert touched.sum() > 0
    ok = ~flag
    assert ok.sum() > 0.9 * ok.size
    err = np.angle(corrected[ok] / expected[ok])
    assert np.max(np.abs(err)) < 1e-6
    np.testing.assert_allclose(np.abs(corrected[ok]), np.abs(expected[ok]), rtol=1e-6)


def test_single_hand_and_nearest_interpolation(tmp_path, new_pair):
    from casacore import tables as pt

    truth = new_pair(PairSpec(n_ant=3, n_time=12, corr_types=("RR",)))
    times = _times(truth.target_ms)
    phase = np.random.default_rng(5).uniform(-np.pi, np.pi, (times.size, 3, 1))
    table = write_gain_table(tmp_path / "rr.G", truth.target_ms, times, phase, None, ["RR"])
    _applycal(truth.target_ms, table, interp="nearest")
    with pt.table(str(truth.target_ms), ack=False) as t:
        d, c = t.getcol("DATA")[:, 0, 0], t.getcol("CORRECTED_DATA")[:, 0, 0]
        it = np.searchsorted(times, t.getcol("TIME"))
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    expected = d * np.exp(-1j * (phase[it, a1, 0] - phase[it, a2, 0]))
    assert np.max(np.abs(np.angle(c / expected))) < 1e-6


def test_refuses_an_existing_table_and_bad_shapes(pair, tmp_path):
    ms = pair.target_ms
    times = _times(ms)
    phase = np.zeros((times.size, 4, 2))
    path = write_gain_table(tmp_path / "a.G", ms, times, phase, None, ["RR", "LL"])
    with pytest.raises(OutputExistsError, match="exists; pass --overwrite"):
        write_gain_table(path, ms, times, phase, None, ["RR", "LL"])
    write_gain_table(path, ms, times, phase + 1.0, None, ["RR", "LL"], overwrite=True)
    with pytest.raises(InputError, match="expected"):
        write_gain_table(tmp_path / "b.G", ms, times, phase[:, :, :1], None, ["RR", "LL"])
    with pytest.raises(InputError, match="one entry per ANTENNA row"):
        write_gain_table(tmp_path / "b.G", ms, times, phase[:, :3], None, ["RR", "LL"])
    with pytest.raises(InputError, match="parallel-hand"):
        write_gain_table(tmp_path / "b.G", ms, times, phase, None, ["RL", "LR"])
    assert not (tmp_path / "b.G").exists()
    # nothing half-written is left beside the tables
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]
