"""Solution-space FPT with real CASA: fringefit/gaincal on 86 GHz -> transfer_table -> applycal at 228 GHz.

The pair is laid out by casatools.simulator (tests/solutions_scene.py): four stations,
20 minutes of 1-s integrations, one 16 x 125 MHz reference window centred on 86 GHz and
two 16 x 125 MHz target windows centred on 227.1 and 229.1 GHz, a point source seen
through per-antenna excess paths (baseline phases wrap 7-10 times at 86 GHz).  The truth is physics:
the target's DATA carry exp(i 2*pi*nu_k*(L_p - L_q)/c), so after a right transfer every
channel of every window and baseline is coherent over the whole track.  Each check runs
the real CASA tasks (fringefit, gaincal, flagdata, applycal) and shows that plausible
wrong transfers fail it: without wrap counting (R*phi, the CFPT analogue) and with the
phase referred to REF_FREQUENCY instead of the table's CHAN_FREQ.
"""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
from casacore import tables as pt

from hitops.casa.runner import run_task
from hitops.casa.tasks import fringefit, gaincal
from hitops.solutions import transfer_table
from hitops.solutions.read import read_solutions
from hitops.solutions.transfer import transfer_window, unwrap_window
from hitops.solutions.write import write_fringe_table
from solutions_scene import (REF_CENTRES_HZ, TARGET_CENTRES_HZ, fringe_fitted_pair,
                             make_solution_pair, refant_sets_halfway)

pytestmark = pytest.mark.slow

COHERENCE_MIN = 0.99


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """The pair and CASA fringefit's 4-s solutions on its reference band."""
    # 4-s solutions at 1-s integrations (fringefit needs >= 2 integrations per interval)
    return fringe_fitted_pair(tmp_path_factory.mktemp("solutions"))


def _coherence(ms, scan_starts=None):
    """Whole-track coherence of CORRECTED_DATA per (window, baseline, channel, correlation);
    with ``scan_starts`` (s from the first row) per scan and field as well."""
    with pt.table(str(ms), ack=False) as t:
        data = t.getcol("CORRECTED_DATA")
        flag = t.getcol("FLAG")
        key = t.getcol("DATA_DESC_ID") * 10000 + t.getcol("ANTENNA1") * 100 + t.getcol("ANTENNA2")
        if scan_starts is not None:
            time = t.getcol("TIME")
            block = np.searchsorted(np.asarray(scan_starts), time - time.min(), side="right")
            key = key + 100000 * (block + 100 * t.getcol("FIELD_ID"))
    out = {}
    for k in np.unique(key):
        sel = key == k
        phasor = np.where(flag[sel], 0.0, np.exp(1j * np.angle(data[sel])))
        n = np.maximum((~flag[sel]).sum(axis=0), 1)
        out[int(k)] = np.abs(phasor.sum(axis=0)) / n
    return out


def _apply(ms, table, scan_starts=None):
    run_task("applycal", vis=str(ms), gaintable=[str(table)], interp=["linear"],
             applymode="calflag", calwt=[False], flagbackup=False)
    return _coherence(ms, scan_starts)


def _worst(coherence):
    return min(float(c.min()) for c in coherence.values())


def test_reads_the_fringe_table_at_chan_freq(solved):
    pair, table = solved
    sol = read_solutions(table, pair.ref_ms)
    assert sol.kind == "Fringe Jones" and sol.has_rates and sol.n_receptor == 2
    (window,) = sol.windows
    # the window centre, not REF_FREQUENCY (the first channel, 85.0625 GHz)
    assert window.ref_freq_hz == pytest.approx(REF_CENTRES_HZ[0])
    with pt.table(f"{table}/SPECTRAL_WINDOW", ack=False) as t:
        assert t.getcol("REF_FREQUENCY")[0] == pytest.approx(85.0625e9)
    assert window.valid.all() and window.times.size == 300
    # the solved delays are the simulated paths (relative to the reference antenna PV)
    it = np.searchsorted(pair.times, window.times)
    relative = (pair.path_m - pair.path_m[:, :1]) / 299_792_458.0
    np.testing.assert_allclose(window.delay_s[:, :, 0], relative[it], atol=5e-13)


def test_fringe_table_transfer_keeps_every_channel_coherent(solved, tmp_path):
    pair, table = solved
    out = tmp_path / "target.fringe"
    report = transfer_table(table, pair.ref_ms, pair.target_ms, out)
    assert report.kind == "Fringe Jones" and report.n_rows == 300 * 4 * 2
    assert report.target_centres_hz == pytest.approx(TARGET_CENTRES_HZ)
    assert sum(a.n_wraps for a in report.antennas) > 50
    with pt.table(f"{out}/SPECTRAL_WINDOW", ack=False) as t:
        np.testing.assert_allclose([t.getcell("CHAN_FREQ", i)[0] for i in range(2)], TARGET_CENTRES_HZ)
    coherence = _apply(pair.target_ms, out)
    assert len(coherence) == 2 * 6
    assert _worst(coherence) >= COHERENCE_MIN
    # without wrap counting (R*phi, the CFPT analogue) the same check fails
    cfpt = transfer_table(table, pair.ref_ms, pair.target_ms, tmp_path / "cfpt.fringe",
                          wrap_counting=False)
    assert not cfpt.wrap_counting
    assert _worst(_apply(pair.target_ms, tmp_path / "cfpt.fringe")) < 0.5


def test_phase_referred_to_ref_frequency_fails(solved, tmp_path):
    """The GUIDE's trap: scaling by REF_FREQUENCY (85.0625 GHz) instead of CHAN_FREQ (86.0)."""
    pair, table = solved
    (window,) = read_solutions(table, pair.ref_ms).windows
    wrong = dataclasses.replace(window, ref_freq_hz=85.0625e9)
    unwrapped = unwrap_window(wrong, max_gap=60.0)
    targets = [transfer_window(unwrapped, spw, 0, centre) for spw, centre in enumerate(TARGET_CENTRES_HZ)]
    write_fringe_table(tmp_path / "wrong.fringe", pair.target_ms, targets, n_ant=4)
    assert _worst(_apply(pair.target_ms, tmp_path / "wrong.fringe")) < COHERENCE_MIN


@pytest.mark.parametrize("gaintype", ["G", "T"])
def test_gaincal_phase_table_transfers(solved, tmp_path, gaintype):
    pair, _ = solved
    table = tmp_path / f"ref.{gaintype}"
    # 4-s phase-only solutions: no rates, so the steps between them must stay below pi
    gaincal(str(pair.ref_ms), str(table), solint="4s", refant="PV,PB", calmode="p",
            gaintype=gaintype, minsnr=3.0, minblperant=2)
    report = transfer_table(table, pair.ref_ms, pair.target_ms, tmp_path / "target.fringe")
    assert report.kind == f"{gaintype} Jones"
    assert max(a.max_residual_rad for a in report.antennas) < np.pi / 2   # gaps included
    assert _worst(_apply(pair.target_ms, tmp_path / "target.fringe")) >= COHERENCE_MIN
    sol = read_solutions(table, pair.ref_ms)
    assert sol.n_receptor == (2 if gaintype == "G" else 1) and not sol.has_rates
    if gaintype == "G":
        # applycal carries a Fringe Jones phase between solutions with the rate: the same
        # transfer written with zero rates (as the table has none) fails
        unwrapped = unwrap_window(sol.windows[0], max_gap=60.0, has_rates=False)
        targets = [dataclasses.replace(transfer_window(unwrapped, spw, 0, centre, has_rates=False),
                                       rate=np.zeros(unwrapped.unwrapped.shape))
                   for spw, centre in enumerate(TARGET_CENTRES_HZ)]
        write_fringe_table(tmp_path / "zero_rates.fringe", pair.target_ms, targets, n_ant=4)
        assert _worst(_apply(pair.target_ms, tmp_path / "zero_rates.fringe")) < COHERENCE_MIN


def test_reference_antenna_change_during_the_track(solved, tmp_path):
    """PV's data flagged for the second half: fringefit refers to PB from then on."""
    pair, _ = solved
    ref_ms, table = refant_sets_halfway(pair, tmp_path)
    with pt.table(str(table), ack=False) as t:
        assert set(t.getcol("ANTENNA2").tolist()) == {0, 1}
    report = transfer_table(table, ref_ms, pair.target_ms, tmp_path / "target.fringe")
    assert len(report.refant_changes) == 1
    change = report.refant_changes[0]
    assert (change.from_antenna, change.to_antenna, change.bridged) == ("PV", "PB", True)
    assert report.common_refant == ("PV",)
    coherence = _apply(pair.target_ms, tmp_path / "target.fringe")
    # PV's baselines lose their second half (flagged solutions flag the data they touch)
    assert _worst(coherence) >= COHERENCE_MIN


def test_several_reference_windows_each_at_its_own_centre(tmp_path):
    """Two reference windows (86 and 88 GHz): each series refers to its own CHAN_FREQ."""
    pair = make_solution_pair(tmp_path, duration_s=600.0, seed=3,
                              ref_centres_hz=(86.0e9, 88.0e9))
    table = tmp_path / "ref.fringe"
    fringefit(str(pair.ref_ms), str(table), solint="4s", refant="PV,PB", minsnr=3.0)
    sol = read_solutions(table, pair.ref_ms)
    assert [w.spw for w in sol.windows] == [0, 1]
    assert [w.ref_freq_hz for w in sol.windows] == pytest.approx([86.0e9, 88.0e9])
    report = transfer_table(table, pair.ref_ms, pair.target_ms, tmp_path / "from88.fringe",
                            ref_spw=1)
    assert report.reference_freq_hz == pytest.approx((88.0e9,))
    assert _worst(_apply(pair.target_ms, tmp_path / "from88.fringe")) >= COHERENCE_MIN


def test_two_fields_in_alternating_scans(tmp_path):
    """Per field, one series; each field's next scan starts a segment (a 120-s gap)."""
    scans = [("M87" if k % 2 == 0 else "3C273", 110.0 * k, 110.0 * k + 100.0) for k in range(6)]
    pair = make_solution_pair(tmp_path, seed=5, scans=scans)
    table = tmp_path / "ref.fringe"
    fringefit(str(pair.ref_ms), str(table), solint="4s", refant="PV,PB", minsnr=3.0)
    sol = read_solutions(table, pair.ref_ms)
    assert sorted({(w.field_name, w.spw) for w in sol.windows}) == [("3C273", 0), ("M87", 0)]
    report = transfer_table(table, pair.ref_ms, pair.target_ms, tmp_path / "target.fringe")
    assert report.n_segments == 6
    with pt.table(str(tmp_path / "target.fringe"), ack=False) as t:
        assert sorted(set(t.getcol("FIELD_ID").tolist())) == [0, 1]
    # every scan of every field coherent; across scans each antenna may carry its own
    # integer per segment (antenna-based: a later per-scan phase calibration absorbs it)
    coherence = _apply(pair.target_ms, tmp_path / "target.fringe", [110.0 * k for k in range(6)])
    assert len(coherence) == 6 * 2 * 6
    assert _worst(coherence) >= COHERENCE_MIN


# ---- bad input: one line naming the table and the remedy, nothing written -------------------

def _refused(error, match, table, ref_ms, target_ms, out):
    with pytest.raises(error, match=match) as info:
        transfer_table(table, ref_ms, target_ms, out)
    assert "\n" not in str(info.value)
    assert not out.exists() and not [p for p in out.parent.iterdir() if "partial" in p.name]
    return str(info.value)


def _copy_ms(src, dst, column, change):
    shutil.copytree(src, dst)
    table = f"{dst}::ANTENNA" if column == "NAME" else str(dst)
    with pt.table(table, readonly=False, ack=False) as t:
        t.putcol(column, change(t.getcol(column)))
    return dst


def test_refuses_a_table_of_another_type(solved, tmp_path):
    from hitops.io.caltable import _create_empty
    from hitops.solutions.errors import SolutionTableError, UnsupportedTableError

    pair, _ = solved
    bandpass = tmp_path / "empty.B"
    _create_empty(str(pair.ref_ms), str(bandpass), "Complex", "B Jones")   # CASA's own layout
    out = tmp_path / "out.fringe"
    _refused(UnsupportedTableError, "'B Jones' table; supported: Fringe Jones, G Jones, T Jones",
             bandpass, pair.ref_ms, pair.target_ms, out)
    _refused(SolutionTableError, "does not exist or is not a CASA table", tmp_path / "nothing",
             pair.ref_ms, pair.target_ms, out)
    _refused(UnsupportedTableError, r"not a calibration table \(type 'Measurement Set'\)",
             pair.ref_ms, pair.ref_ms, pair.target_ms, out)


def test_refuses_a_table_solved_on_another_set(solved, tmp_path):
    from hitops.solutions.errors import TableMismatchError

    pair, table = solved
    out = tmp_path / "out.fringe"
    _refused(TableMismatchError, "spectral windows", table, pair.target_ms, pair.target_ms, out)
    renamed = _copy_ms(pair.ref_ms, tmp_path / "renamed.ms", "NAME",
                       lambda names: [*names[:3], "KP"])
    _refused(TableMismatchError, r"antennas \['PV', 'PB', 'AP', 'GL'\]", table, renamed,
             pair.target_ms, out)
    next_day = _copy_ms(pair.ref_ms, tmp_path / "next_day.ms", "TIME", lambda t: t + 86400.0)
    _refused(TableMismatchError, "solution time", table, next_day, pair.target_ms, out)
    target_next_day = _copy_ms(pair.target_ms, tmp_path / "target_next_day.ms", "TIME",
                               lambda t: t + 86400.0)
    _refused(TableMismatchError, "does not overlap the solutions", table, pair.ref_ms,
             target_next_day, out)


def test_refuses_a_station_without_unflagged_solutions(solved, tmp_path):
    from hitops.solutions.errors import NoSolutionsError

    pair, table = solved
    flagged = tmp_path / "gl_flagged.fringe"
    shutil.copytree(table, flagged)
    run_task("flagdata", vis=str(flagged), mode="manual", antenna="GL", flagbackup=False)
    message = _refused(NoSolutionsError, "no unflagged solution for station", flagged, pair.ref_ms,
                       pair.target_ms, tmp_path / "out.fringe")
    assert "GL" in message and "PV" not in message


def test_refuses_solutions_too_far_apart_to_count(solved, tmp_path):
    from hitops.solutions.errors import SolutionIntervalError

    pair, _ = solved
    table = tmp_path / "ref60.G"
    gaincal(str(pair.ref_ms), str(table), solint="60s", refant="PV,PB", calmode="p",
            minsnr=3.0, minblperant=2)
    _refused(SolutionIntervalError, "moves by more than pi between solutions 60 s apart", table,
             pair.ref_ms, pair.target_ms, tmp_path / "out.fringe")
