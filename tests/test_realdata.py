"""hitops on real observations: the EHT's public M87 data of 2017 April 5 (tests/data/eht2017-m87).

Two bands (227.07 and 229.07 GHz, R = 1.0088) as the EHT released them, imported
with CASA importuvfits, which names the stations '1'..'8' and keeps the codes in
ANTENNA::STATION.  What is checked against an independent computation here:

* stations are paired by code, also after one band loses a station and its
  antennas are renumbered (then name '5' is PV in one band and LM in the other);
* every written CFPT sample equals the target sample times exp(-i R arg(reference))
  of the reference row with the same station codes and time (1e-6 rad), and at
  least 95% of the samples that such pairing can calibrate are written;
* the antenna tracker keeps the target's closure phases (1e-6 rad): M87 is resolved;
* a rerun with --overwrite gives byte-identical columns and flags;
* a table held open by another process gives a message within seconds and an exit
  within --lock-timeout.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.diagnose.closures import row_closures

HITOPS = Path(sys.executable).with_name("hitops")

pytestmark = pytest.mark.slow


@pytest.fixture
def pair(eht_imported, tmp_path):
    """A fresh copy of the imported pair (tests/conftest.py, imported once) for one test."""
    lo, hi = tmp_path / "lo.ms", tmp_path / "hi.ms"
    shutil.copytree(eht_imported[0], lo)
    shutil.copytree(eht_imported[1], hi)
    return lo, hi


def read(ms, *columns):
    with pt.table(str(ms), ack=False) as t:
        return [t.getcol(c) for c in columns]


def codes(ms):
    with pt.table(f"{ms}::ANTENNA", ack=False) as t:
        return list(t.getcol("STATION"))


def drop_station(ms: Path, code: str) -> None:
    """Remove one station from a set as if it had never been there: its rows, its ANTENNA
    row, and the antennas renumbered (NAME '1'..'N-1', as importuvfits would write).

    importuvfits' storage managers cannot remove rows, so the remaining rows are copied
    (deep, with the subtables) to a new set that replaces the old one.
    """
    index = codes(ms).index(code)
    kept = ms.with_name(ms.name + ".kept")
    with pt.table(str(ms), ack=False) as t:
        with t.query(f"ANTENNA1!={index} && ANTENNA2!={index}") as sel:
            sel.copy(str(kept), deep=True).close()
    shutil.rmtree(ms)
    kept.rename(ms)
    with pt.table(str(ms), readonly=False, ack=False) as t:
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        t.putcol("ANTENNA1", np.where(a1 > index, a1 - 1, a1))
        t.putcol("ANTENNA2", np.where(a2 > index, a2 - 1, a2))
    with pt.table(f"{ms}::ANTENNA", readonly=False, ack=False) as t:
        t.removerows([index])
        t.putcol("NAME", [str(i + 1) for i in range(t.nrows())])


def code_paired_reference(ref_ms, tgt_ms, tolerance=1.0):
    """For each target row: the reference visibility of the row with the same station codes
    and time (conjugated when the order is reversed), NaN where there is none."""
    r_codes, t_codes = codes(ref_ms), codes(tgt_ms)
    r_time, r_a1, r_a2, r_data, r_flag = read(ref_ms, "TIME", "ANTENNA1", "ANTENNA2", "DATA", "FLAG")
    t_time, t_a1, t_a2 = read(tgt_ms, "TIME", "ANTENNA1", "ANTENNA2")
    r_data = np.where(r_flag, np.nan, r_data)[:, 0, :]
    lookup = {}
    for i in range(r_time.size):
        key = (int(round(r_time[i] / tolerance)), r_codes[r_a1[i]], r_codes[r_a2[i]])
        lookup[key] = r_data[i]
        key_rev = (key[0], key[2], key[1])
        # RL of p-q is the conjugate of LR of q-p: swap the cross hands (RR RL LR LL)
        lookup.setdefault(key_rev, np.conj(r_data[i][[0, 2, 1, 3]]))
    out = np.full((t_time.size, 4), np.nan + 0j, dtype=np.complex128)
    for i in range(t_time.size):
        key = (int(round(t_time[i] / tolerance)), t_codes[t_a1[i]], t_codes[t_a2[i]])
        if key in lookup:
            out[i] = lookup[key]
    return out


def check_cfpt_against_code_pairing(ref_ms, tgt_ms, report):
    ratio = report["ratio"]
    data, flag, cfpt = read(tgt_ms, "DATA", "FLAG", "CFPT_DATA")
    data, flag, cfpt = data[:, 0, :], flag[:, 0, :], cfpt[:, 0, :]
    backup = read(tgt_ms, "FLAG_HITOPS_BACKUP")[0][:, 0, :] if "FLAG_HITOPS_BACKUP" in \
        pt.table(str(tgt_ms), ack=False).colnames() else flag
    ref = code_paired_reference(ref_ms, tgt_ms)
    expected = data * np.exp(-1j * ratio * np.angle(ref))
    written = ~flag
    assert written.sum() > 0
    diff = np.angle(cfpt[written] * np.conj(expected[written]))
    assert np.all(np.isfinite(diff))
    assert np.max(np.abs(diff)) < 1e-6
    # samples that pairing by code can calibrate: target unflagged, non-zero, a reference
    # sample with the same codes and time, unflagged and non-zero
    can = (~backup & (np.abs(data) > 0) & np.isfinite(ref) & (np.abs(ref) > 0))
    assert (written & can).sum() >= 0.95 * can.sum()
    assert not np.any(written & ~can)
    return can


def test_stations_paired_by_code_and_every_sample_checked(pair):
    ref, tgt = pair
    report = calibrate_flat(str(ref), str(tgt), method="cfpt,pwc")
    assert {(e["reference"], e["target"]) for e in report["stations"]} == {
        (c, c) for c in codes(tgt)}
    can = check_cfpt_against_code_pairing(ref, tgt, report)
    assert can.sum() > 10_000
    # logs and tables name stations by code, never by the importuvfits numbers
    names = [e["baseline"] for e in report["wraps"]]
    assert "AA-AP" in names and not any(n[0].isdigit() for n in names)


def test_one_band_without_a_station_still_pairs_by_code(pair, caplog):
    ref, tgt = pair
    drop_station(ref, "LM")
    assert codes(ref)[4] == "PV" and codes(tgt)[4] == "LM"   # name '5' differs between bands
    with caplog.at_level("WARNING", logger="hitops"):
        report = calibrate_flat(str(ref), str(tgt), method="cfpt")
    assert "target station LM" in caplog.text and "AA-LM" in caplog.text
    check_cfpt_against_code_pairing(ref, tgt, report)
    t_a1, t_a2, flag = read(tgt, "ANTENNA1", "ANTENNA2", "FLAG")
    lm = codes(tgt).index("LM")
    assert flag[(t_a1 == lm) | (t_a2 == lm)].all()


def closure_phases(ms, column, flag):
    """{(time, triangle): closure phase} of RR over every triangle of unflagged baselines."""
    time, a1, a2, vis = read(ms, "TIME", "ANTENNA1", "ANTENNA2", column)
    vis = vis[:, 0, 0]
    return row_closures(time, a1, a2, vis, ~flag[:, 0, 0] & (np.abs(vis) > 0))


def test_antenna_tracker_keeps_the_closure_phases_of_m87(pair):
    ref, tgt = pair
    calibrate_flat(str(ref), str(tgt), method="pwc", tracker="antenna")
    flag = read(tgt, "FLAG")[0]
    before = closure_phases(tgt, "DATA", flag)
    after = closure_phases(tgt, "PWC_DATA", flag)
    assert len(after) > 1000 and after.keys() == before.keys()
    diff = np.array([after[k] - before[k] for k in after])
    diff = (diff + np.pi) % (2 * np.pi) - np.pi
    assert np.max(np.abs(diff)) < 1e-6
    # the source is resolved: its closure phases are far from zero (what a baseline method
    # would overwrite with R times the reference band's)
    closures = np.array(list(before.values()))
    assert np.median(np.abs((closures + np.pi) % (2 * np.pi) - np.pi)) > 0.1


def test_rerun_with_overwrite_is_byte_identical(pair):
    ref, tgt = pair
    calibrate_flat(str(ref), str(tgt), method="pwc,cfpt")
    first = read(tgt, "PWC_DATA", "CFPT_DATA", "FLAG", "FLAG_HITOPS_BACKUP")
    calibrate_flat(str(ref), str(tgt), method="pwc,cfpt", overwrite=True)
    second = read(tgt, "PWC_DATA", "CFPT_DATA", "FLAG", "FLAG_HITOPS_BACKUP")
    for a, b in zip(first, second):
        assert a.tobytes() == b.tobytes()


def test_a_table_held_open_elsewhere_is_named_and_the_wait_is_bounded(pair):
    ref, tgt = pair
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\nfrom casacore import tables as pt\n"
         "t = pt.table(sys.argv[1], ack=False)\nt.getcol('TIME')\n"
         "print('open', flush=True)\ntime.sleep(60)\n", str(tgt)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        started = time.monotonic()
        proc = subprocess.Popen([str(HITOPS), "calibrate", str(ref), str(tgt), "--lock-timeout",
                                 "4"], stderr=subprocess.PIPE, text=True)
        first = proc.stderr.readline()
        said = time.monotonic() - started
        rest = proc.stderr.read()
        proc.wait(timeout=60)
        ended = time.monotonic() - started
    finally:
        holder.kill()
        holder.wait()
    text = first + rest
    assert said < 10 and "locked by another process" in first and f"pid {holder.pid}" in first
    assert proc.returncode == 2 and ended < 4 + 15
    assert "waited 4 s" in text and "Traceback" not in text
    assert "PWC_DATA" not in pt.table(str(tgt), ack=False).colnames()
