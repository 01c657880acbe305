"""hitops.io.convert: UVFITS (and FITS-IDI, tests/test_convert_fitsidi.py) inputs of hitops calibrate.

* the direct UVFITS reader gives the same Measurement Set as CASA importuvfits,
  for files written by CASA exportuvfits, by hitops and by the EHT (public data);
* scans survive a round trip through CASA exportuvfits (which writes no scan
  table): the converted sets get one scan per gap, and calibrate sees them;
* a conversion is reused while its source is unchanged, never touches the source
  and leaves nothing half-written when it fails;
* bad input (no antenna table, IFs the FQ table does not describe, several frequency
  setups, truncated files,
  stations unknown to the other band, an existing --export-uvfits file) gives
  one line naming the file and the remedy, and changes no input.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate import files as calibrate_files
from hitops.testing import PairSpec, Signal
from hitops.errors import InputError, OutputExistsError, StationError
from hitops.io import convert
from hitops.io.fits import bintable as _bintable, card as _card, read_headers
from hitops.io.uvfits import export_uvfits

REALDATA = Path(__file__).resolve().parent / "data" / "eht2017-m87"   # in every checkout
EHT_LO = REALDATA / "SR1_M87_2017_095_lo_hops_netcal_StokesI.uvfits"
EHT_HI = REALDATA / "SR1_M87_2017_095_hi_hops_netcal_StokesI.uvfits"


def digest(*paths):
    out = {}
    for p in paths:
        p = Path(p)
        files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file())
        for f in files:
            if f.name != "table.lock":
                out[str(f)] = hashlib.sha1(f.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo scene (6 scans, 60 s gaps) as UVFITS written by CASA exportuvfits."""
    from hitops.casa.runner import run_task
    from hitops.simulate import simulate

    work = tmp_path_factory.mktemp("demo")
    sets = simulate("demo", work, duration=1800, scan_length=240, scan_gap=60)
    files = {}
    for band, ms in sets.items():
        out = work / f"demo-{band}.uvfits"
        run_task("exportuvfits", vis=str(ms), fitsfile=str(out), datacolumn="data")
        files[band] = out
    return work, sets, files


def read_ms(ms):
    """Main columns sorted by (time, station pair) and the subtables that matter."""
    from casacore import tables as pt

    from hitops.io.stations import read_stations

    codes = read_stations(str(ms)).codes
    with pt.table(str(ms), ack=False) as t:
        cols = {k: t.getcol(k) for k in ("TIME", "ANTENNA1", "ANTENNA2", "UVW", "DATA", "FLAG",
                                         "WEIGHT", "SCAN_NUMBER", "INTERVAL")}
    pairs = np.array([f"{codes[a]}-{codes[b]}" for a, b in zip(cols["ANTENNA1"], cols["ANTENNA2"])])
    order = np.lexsort((pairs, np.round(cols["TIME"], 2)))
    out = {k: v[order] for k, v in cols.items()}
    out["pairs"] = pairs[order]
    sub = {}
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        sub["freq"] = t.getcol("CHAN_FREQ")
    with pt.table(f"{ms}::POLARIZATION", ack=False) as t:
        sub["corr"] = t.getcol("CORR_TYPE").tolist()
    with pt.table(f"{ms}::FIELD", ack=False) as t:
        direction = t.getcol("PHASE_DIR").ravel()
        sub["dir"] = [direction[0] % (2 * np.pi), direction[1]]
    with pt.table(f"{ms}::ANTENNA", ack=False) as t:
        sub["positions"] = dict(zip(codes, t.getcol("POSITION").tolist()))
    return out, sub


def assert_same_sets(a, b, scans=True):
    (ca, sa), (cb, sb) = read_ms(a), read_ms(b)
    np.testing.assert_array_equal(ca["pairs"], cb["pairs"])
    np.testing.assert_array_equal(ca["TIME"], cb["TIME"])
    np.testing.assert_array_equal(ca["UVW"], cb["UVW"])
    np.testing.assert_array_equal(ca["DATA"], cb["DATA"])
    np.testing.assert_array_equal(ca["FLAG"], cb["FLAG"])
    np.testing.assert_array_equal(ca["WEIGHT"], cb["WEIGHT"])
    np.testing.assert_array_equal(ca["INTERVAL"], cb["INTERVAL"])
    # scans: the same grouping of rows (numbers may differ)
    if not scans:
        return
    _, ia = np.unique(ca["SCAN_NUMBER"], return_inverse=True)
    _, ib = np.unique(cb["SCAN_NUMBER"], return_inverse=True)
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_array_equal(sa["freq"], sb["freq"])
    assert sa["corr"] == sb["corr"]
    np.testing.assert_allclose(sa["dir"], sb["dir"], rtol=0, atol=1e-9)
    assert sa["positions"] == sb["positions"]


# ---------------------------------------------------------------- formats and readers

def test_detect_format(demo, tmp_path):
    _, sets, files = demo
    assert convert.detect_format(sets["86"]) == "ms"
    assert convert.detect_format(files["86"]) == "uvfits"
    assert convert.detect_format(tmp_path / "missing.ms") == "ms"   # check_ms reports it
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(InputError, match="neither a Measurement Set .* nor a FITS file"):
        convert.detect_format(text, "REF")


def _hitops_written(tmp_path, new_pair):
    from casacore import tables as pt

    truth = new_pair(PairSpec(n_ant=4, n_time=40, dt=2.0, n_scans=2,
                              corr_types=("RR", "RL", "LR", "LL"),
                              signal=Signal(sigma_target=0.2)))
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        flag[::7, 0, 1] = True
        t.putcol("FLAG", flag)
        t.putcol("UVW", np.random.default_rng(0).normal(0, 3e6, (t.nrows(), 3)))
    out = tmp_path / "hitops.uvfits"
    export_uvfits(truth.target_ms, out, "DATA")
    return out


@pytest.mark.parametrize("writer", ["casa-exportuvfits", "hitops", "eht-public"])
def test_direct_reader_equals_casa_importuvfits(writer, demo, tmp_path, new_pair):
    if writer == "casa-exportuvfits":
        source = demo[2]["230"]
    elif writer == "hitops":
        source = _hitops_written(tmp_path, new_pair)
    else:
        if not EHT_LO.exists():
            pytest.skip(f"{EHT_LO} not present")
        source = EHT_LO
    direct = convert.convert(source, tmp_path / "direct.ms")
    assert direct.tool.startswith("hitops.io.convert")
    casa = convert.convert(source, tmp_path / "casa.ms", reader="casa")
    assert casa.tool == "casatasks.importuvfits"
    if writer == "hitops":
        # hitops writes an AIPS NX (scan) table: the direct reader keeps its 2 contiguous
        # scans, CASA importuvfits does not read NX tables and finds no gap to split at
        assert (direct.n_scans, casa.n_scans) == (2, 1)
    else:
        assert direct.n_scans == casa.n_scans
    assert_same_sets(direct.ms, casa.ms, scans=writer != "hitops")


def test_scans_survive_a_casa_round_trip(demo, caplog):
    work, sets, files = demo
    from casacore import tables as pt

    with pt.table(str(sets["230"]), ack=False) as t:
        n_scans = np.unique(t.getcol("SCAN_NUMBER")).size
    assert n_scans == 6
    for reader in ("auto", "casa"):
        c = convert.convert(files["230"], work / f"scans-{reader}.ms", reader=reader)
        assert c.n_scans == n_scans, reader
    # and calibrate sees them: one tracking restart per scan, wraps not counted across gaps
    caplog.set_level(logging.INFO)
    rep = calibrate_flat(files["86"], files["230"], workdir=str(work / "cal"), method="pwc",
                    no_verdict=True)
    assert [c["n_scans"] for c in rep["conversions"]] == [n_scans, n_scans]
    assert {c["band"] for c in rep["conversions"]} == {"ref", "target"}
    matched = [r.getMessage() for r in caplog.records if r.getMessage().startswith("matched ")]
    assert matched and f", {n_scans} scans)" in matched[-1], matched


# ---------------------------------------------------------------- reuse, safety

def test_reused_while_unchanged_and_source_untouched(demo, tmp_path):
    _, _, files = demo
    source = tmp_path / "t.uvfits"
    source.write_bytes(files["230"].read_bytes())
    before = digest(source)
    first = convert.ensure_ms(source, "TARGET", str(tmp_path / "w"))
    assert first.converted and not first.reused
    assert first.ms == str(tmp_path / "w" / "t.uvfits.ms")
    stamp = os.stat(Path(first.ms) / "table.dat").st_mtime_ns
    second = convert.ensure_ms(source, "TARGET", str(tmp_path / "w"))
    assert second.reused and not second.converted
    assert os.stat(Path(first.ms) / "table.dat").st_mtime_ns == stamp
    assert digest(source) == before
    # a changed source is converted again
    st = os.stat(source)
    os.utime(source, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    third = convert.ensure_ms(source, "TARGET", str(tmp_path / "w"))
    assert third.converted
    # default workdir: beside the input
    beside = convert.ensure_ms(source, "TARGET")
    assert beside.ms == str(tmp_path / "t.uvfits.ms")
    # a set hitops did not convert is never replaced
    (tmp_path / "x").mkdir()
    other = tmp_path / "x" / "t.uvfits"
    other.write_bytes(source.read_bytes())
    (tmp_path / "x" / "t.uvfits.ms").mkdir()
    (tmp_path / "x" / "t.uvfits.ms" / "table.dat").write_text("not ours")
    with pytest.raises(InputError, match="was not converted by hitops from this file"):
        convert.ensure_ms(other, "TARGET")
    assert (tmp_path / "x" / "t.uvfits.ms" / "table.dat").read_text() == "not ours"


def test_failed_conversion_leaves_nothing(demo, tmp_path, monkeypatch):
    _, _, files = demo

    def boom(*args, **kwargs):
        raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(convert, "assign_scans", boom)
    with pytest.raises(RuntimeError, match="simulated"):
        convert.ensure_ms(files["86"], "REF", str(tmp_path))
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- bad input

def _primary_end(raw_path):
    header, start, n = read_headers(raw_path)[0]
    return start + -(-n // 2880) * 2880


def _set_cards(raw: bytes, values) -> bytes:
    """Replace cards of the primary header (same length)."""
    out = bytearray(raw)
    for i in range(0, 2880 * 10, 80):
        key = out[i:i + 8].decode().strip()
        if key == "END":
            break
        if key in values:
            out[i:i + 80] = _card(key, values[key]).encode()
    return bytes(out)


def _bad_files(base: Path, tmp_path: Path):
    raw = base.read_bytes()
    end = _primary_end(base)
    headers = read_headers(base)
    files = {}
    files["no-antenna-table"] = raw[:end]
    gcount = headers[0][0]["GCOUNT"]
    assert gcount % 2 == 0
    files["two-ifs"] = _set_cards(raw, {"NAXIS5": 2, "GCOUNT": gcount // 2})
    fq = _bintable("AIPS FQ", [("FRQSEL", "1J", "", [1, 2]), ("IF FREQ", "1D", "HZ", [0.0, 0.0]),
                               ("CH WIDTH", "1E", "HZ", [2e9, 2e9]),
                               ("TOTAL BANDWIDTH", "1E", "HZ", [2e9, 2e9]),
                               ("SIDEBAND", "1J", "", [1, 1])], [("NO_IF", 1)], 2)
    # each HDU's bytes: from where the previous one ends to its padded data end
    pieces, start = {}, 0
    for header, data_start, n in headers:
        stop = data_start + -(-n // 2880) * 2880
        pieces[header.get("EXTNAME", "PRIMARY")] = raw[start:stop]
        start = stop
    files["two-frequency-setups"] = pieces["PRIMARY"] + pieces["AIPS AN"] + fq
    files["truncated"] = raw[:end - 5000]
    out = {}
    for name, data in files.items():
        p = tmp_path / f"{name}.uvfits"
        p.write_bytes(data)
        out[name] = p
    return out


BAD = {
    "no-antenna-table": r"no-antenna-table\.uvfits' has no antenna table \(AIPS AN\)",
    "two-ifs": r"two-ifs\.uvfits' holds 2 IFs on its IF axis but its AIPS FQ table describes 1",
    "two-frequency-setups": r"two-frequency-setups\.uvfits' holds 2 frequency setups",
    "truncated": r"truncated\.uvfits' is truncated",
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_uvfits_one_line_and_inputs_unchanged(case, demo, tmp_path):
    _, _, files = demo
    bad = _bad_files(files["230"], tmp_path)[case]
    ref = tmp_path / "ref.uvfits"
    ref.write_bytes(files["86"].read_bytes())
    before = digest(ref, bad)
    with pytest.raises(InputError, match=BAD[case]) as err:
        calibrate_flat(ref, bad, workdir=str(tmp_path / "w"))
    assert "\n" not in str(err.value)
    assert digest(ref, bad) == before
    assert not (tmp_path / "w" / bad.name).with_suffix(".uvfits.ms").exists()
    assert not list(tmp_path.glob("w/*partial*"))


def test_stations_unknown_to_the_other_band(tmp_path, new_pair, caplog):
    # no station in common: nothing can be calibrated, one line naming both converted sets
    truth = new_pair(PairSpec(n_ant=3, n_time=30, target_names=["XA", "XB", "XC"]))
    ref, tgt = tmp_path / "ref.uvfits", tmp_path / "tgt.uvfits"
    export_uvfits(truth.ref_ms, ref, "DATA")
    export_uvfits(truth.target_ms, tgt, "DATA")
    before = digest(ref, tgt)
    with pytest.raises(StationError, match=r"no baseline of .*tgt\.uvfits\.ms has both stations "
                                           r"in .*ref\.uvfits\.ms.*--antenna-map") as err:
        calibrate_flat(ref, tgt, workdir=str(tmp_path / "w"))
    assert "\n" not in str(err.value)
    assert digest(ref, tgt) == before
    # one station unknown: calibrate's policy is a warning naming it, its baselines flagged
    part = new_pair(PairSpec(n_ant=4, n_time=30, target_names=["AP", "SM", "PV", "XX"]),
                    tmp_path / "p")
    export_uvfits(part.ref_ms, tmp_path / "p" / "ref.uvfits", "DATA")
    export_uvfits(part.target_ms, tmp_path / "p" / "tgt.uvfits", "DATA")
    rep = calibrate_flat(tmp_path / "p" / "ref.uvfits", tmp_path / "p" / "tgt.uvfits", no_verdict=True)
    assert any("target station XX of" in r.getMessage() and "tgt.uvfits.ms" in r.getMessage()
               for r in caplog.records)
    assert rep["samples"]["no_reference_row"] > 0


def test_existing_export_path_needs_overwrite(demo, tmp_path):
    _, _, files = demo
    out = tmp_path / "out.uvfits"
    out.write_text("an earlier result")
    before = digest(files["86"], files["230"], out)
    with pytest.raises(OutputExistsError, match=r"--export-uvfits '.*out\.uvfits' exists; pass "
                                                r"--overwrite"):
        calibrate_flat(files["86"], files["230"], workdir=str(tmp_path / "w"), export_uvfits=str(out))
    assert digest(files["86"], files["230"], out) == before
    assert not (tmp_path / "w").exists()      # refused before any conversion


def test_cli_bad_input_is_one_line_exit_2(demo, tmp_path):
    _, _, files = demo
    bad = _bad_files(files["230"], tmp_path)["no-antenna-table"]
    hitops = Path(sys.executable).parent / "hitops"
    done = subprocess.run([str(hitops), "calibrate", str(files["86"]), str(bad), "--workdir",
                           str(tmp_path / "w")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    lines = [line for line in done.stderr.splitlines() if "no antenna table" in line]
    assert len(lines) == 1 and "no-antenna-table.uvfits" in lines[0]


# ---------------------------------------------------------------- real data, end to end

@pytest.mark.skipif(not EHT_HI.exists(), reason="public EHT files not present")
def test_public_eht_uvfits_pair_end_to_end(tmp_path):
    hitops = Path(sys.executable).parent / "hitops"
    out = tmp_path / "hi-pwc.uvfits"
    done = subprocess.run([str(hitops), "calibrate", str(EHT_LO), str(EHT_HI), "--workdir",
                           str(tmp_path), "--tracker", "antenna", "--export-uvfits", str(out),
                           "--no-verdict"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((tmp_path / (EHT_HI.name + ".ms.hitops-calibrate.json")).read_text())
    assert [c["n_scans"] for c in report["conversions"]] == [18, 18]   # 17 + a 190 s gap
    assert report["stations"]
    assert report["export_uvfits"]["rows"] == 6458
    headers = read_headers(out)
    assert headers[0][0]["GCOUNT"] == 6458
    assert [h.get("EXTNAME") for h, _, _ in headers][1:] == ["AIPS AN", "AIPS FQ", "AIPS NX"]


def test_caltable_checks_for_the_lead(demo, tmp_path):
    # stages 1 and 2 on their own: --caltable needs the antenna tracker (the mode's refusal,
    # hitops/calibrate/modes.py), and prepare_inputs checks an existing table before anything
    # is converted or written
    from hitops.calibrate.inputs import CalibrateOptions
    from hitops.calibrate.modes import check_options
    _, _, files = demo

    def options(**flags):
        return CalibrateOptions.from_flat(dict(ref_ms=files["86"], target_ms=files["230"],
                                               workdir=str(tmp_path / "w"), **flags))

    with pytest.raises(InputError, match=r"--caltable '.*x\.G' needs --tracker antenna"):
        check_options(options(caltable=str(tmp_path / "x.G"), tracker="count"), ["pwc"])
    (tmp_path / "old.G").mkdir()
    old = options(caltable=str(tmp_path / "old.G"), tracker="antenna")
    check_options(old, ["pwc"])
    with pytest.raises(OutputExistsError, match=r"--caltable '.*old\.G' exists; pass --overwrite"):
        calibrate_files.prepare_inputs(old)
    assert not (tmp_path / "w").exists()
