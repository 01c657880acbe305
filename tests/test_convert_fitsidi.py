"""FITS-IDI inputs of hitops calibrate (CASA importfitsidi) and their bad-input check.

No tool here writes FITS-IDI, so the test writes a minimal file itself (the
tables CASA importfitsidi needs: ARRAY_GEOMETRY, SOURCE, FREQUENCY, ANTENNA,
UV_DATA), with FITS-IDI's sign convention (visibilities conjugated relative to
UVFITS and the Measurement Set; importfitsidi conjugates them back).
"""

from __future__ import annotations

import datetime

import numpy as np

from hitops.calibrate import calibrate_flat
from hitops.testing import PairSpec, Storage, expected_pwc_phase, wrap
from hitops.io import convert
from hitops.io.fits import bintable as _bintable, card as _card, gst0_deg as _gst0_deg
from hitops.io.fits import header_bytes as _header_bytes


def write_fitsidi(path, ms, n_band=1):
    """The DATA column of a single-channel Measurement Set as a FITS-IDI file."""
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        time_s, a1, a2 = t.getcol("TIME"), t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        uvw, vis = t.getcol("UVW"), t.getcol("DATA")[:, 0, :]
    with pt.table(f"{ms}::ANTENNA", ack=False) as t:
        names, positions = list(t.getcol("NAME")), t.getcol("POSITION")
    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        freq, bw = float(t.getcol("CHAN_FREQ")[0, 0]), float(t.getcol("TOTAL_BANDWIDTH")[0])
    n_ant, n_row, n_st = len(names), time_s.size, vis.shape[1]
    mjd0 = np.floor(time_s.min() / 86400.0)
    jd0 = mjd0 + 2400000.5
    rdate = (datetime.date(1858, 11, 17) + datetime.timedelta(days=int(mjd0))).isoformat()
    nb = n_band
    common = [("OBSCODE", "HITOPS"), ("NO_STKD", n_st), ("STK_1", -1), ("NO_BAND", nb),
              ("NO_CHAN", 1), ("REF_FREQ", freq), ("CHAN_BW", bw), ("REF_PIXL", 1.0),
              ("TABREV", 1)]
    out = _header_bytes([_card("SIMPLE", True), _card("BITPIX", 8), _card("NAXIS", 0),
                         _card("EXTEND", True), _card("GROUPS", True), _card("GCOUNT", 0),
                         _card("PCOUNT", 0), _card("CORRELAT", "DIFX"),
                         _card("FXCORVER", "1.0"), _card("DATE-OBS", rdate)])
    out += _bintable("ARRAY_GEOMETRY", [
        ("ANNAME", "8A", "", names), ("STABXYZ", "3D", "METERS", positions),
        ("DERXYZ", "3E", "METERS/SEC", np.zeros((n_ant, 3))), ("ORBPARM", "0D", "", None),
        ("NOSTA", "1J", "", np.arange(1, n_ant + 1)), ("MNTSTA", "1J", "", np.zeros(n_ant)),
        ("STAXOF", "3E", "METERS", np.zeros((n_ant, 3)))],
        common + [("ARRAYX", 0.0), ("ARRAYY", 0.0), ("ARRAYZ", 0.0), ("ARRNAM", "VLBA"),
                  ("FRAME", "GEOCENTRIC"), ("NUMORB", 0), ("FREQ", freq), ("TIMSYS", "UTC"),
                  ("RDATE", rdate), ("DEGPDY", 360.9856449733), ("GSTIA0", _gst0_deg(jd0)),
                  ("POLARX", 0.0), ("POLARY", 0.0), ("UT1UTC", 0.0), ("IATUTC", 37.0)], n_ant)
    zeros = np.zeros((1, nb))
    out += _bintable("SOURCE", [
        ("SOURCE_ID", "1J", "", [1]), ("SOURCE", "16A", "", ["SYNTH"]), ("QUAL", "1J", "", [0]),
        ("CALCODE", "4A", "", [""]), ("FREQID", "1J", "", [1]),
        ("IFLUX", f"{nb}E", "JY", zeros), ("QFLUX", f"{nb}E", "JY", zeros),
        ("UFLUX", f"{nb}E", "JY", zeros), ("VFLUX", f"{nb}E", "JY", zeros),
        ("ALPHA", f"{nb}E", "", zeros), ("FREQOFF", f"{nb}D", "HZ", zeros),
        ("RAEPO", "1D", "DEGREES", [187.7]), ("DECEPO", "1D", "DEGREES", [12.39]),
        ("EQUINOX", "8A", "", ["J2000"]), ("RAAPP", "1D", "DEGREES", [187.7]),
        ("DECAPP", "1D", "DEGREES", [12.39]), ("SYSVEL", f"{nb}D", "METERS/SEC", zeros),
        ("VELTYP", "8A", "", ["GEOCENTR"]), ("VELDEF", "8A", "", ["OPTICAL"]),
        ("RESTFREQ", f"{nb}D", "HZ", zeros), ("PMRA", "1D", "DEG/DAY", [0.0]),
        ("PMDEC", "1D", "DEG/DAY", [0.0]), ("PARALLAX", "1E", "ARCSEC", [0.0]),
        ("EPOCH", "1D", "YEARS", [2000.0])], common, 1)
    out += _bintable("FREQUENCY", [
        ("FREQID", "1J", "", [1]), ("BANDFREQ", f"{nb}D", "HZ", np.arange(nb)[None] * bw),
        ("CH_WIDTH", f"{nb}E", "HZ", np.full((1, nb), bw)),
        ("TOTAL_BANDWIDTH", f"{nb}E", "HZ", np.full((1, nb), bw)),
        ("SIDEBAND", f"{nb}J", "", np.ones((1, nb))), ("BB_CHAN", f"{nb}J", "", zeros)],
        common, 1)
    out += _bintable("ANTENNA", [
        ("TIME", "1D", "DAYS", np.full(n_ant, 0.5)), ("TIME_INTERVAL", "1E", "DAYS", np.ones(n_ant)),
        ("ANNAME", "8A", "", names), ("ANTENNA_NO", "1J", "", np.arange(1, n_ant + 1)),
        ("ARRAY", "1J", "", np.ones(n_ant)), ("FREQID", "1J", "", np.ones(n_ant)),
        ("NO_LEVELS", "1J", "", np.full(n_ant, 4)), ("POLTYA", "1A", "", ["R"] * n_ant),
        ("POLAA", f"{nb}E", "DEGREES", np.zeros((n_ant, nb))),
        ("POLCALA", f"{2 * nb}E", "", np.zeros((n_ant, 2 * nb))),
        ("POLTYB", "1A", "", ["L"] * n_ant), ("POLAB", f"{nb}E", "DEGREES", np.zeros((n_ant, nb))),
        ("POLCALB", f"{2 * nb}E", "", np.zeros((n_ant, 2 * nb)))],
        common + [("NOPCAL", 2), ("POLTYPE", "APPROX")], n_ant)
    flux = np.zeros((n_row, nb, n_st, 2), np.float32)
    conj = np.conj(vis)                       # FITS-IDI's sign convention
    flux[..., 0], flux[..., 1] = conj.real[:, None, :], conj.imag[:, None, :]
    axes = [("COMPLEX", 2, 1.0, 1.0), ("STOKES", n_st, -1.0, -1.0), ("FREQ", 1, freq, bw),
            ("BAND", nb, 1.0, 1.0), ("RA", 1, 0.0, 0.0), ("DEC", 1, 0.0, 0.0)]
    matrix = [("NMATRIX", 1), ("MAXIS", 6)]
    for k, (name, n, crval, cdelt) in enumerate(axes, start=1):
        matrix += [(f"MAXIS{k}", n), (f"CTYPE{k}", name), (f"CDELT{k}", cdelt),
                   (f"CRPIX{k}", 1.0), (f"CRVAL{k}", crval)]
    out += _bintable("UV_DATA", [
        ("UU---SIN", "1E", "SECONDS", uvw[:, 0] / 299792458.0),
        ("VV---SIN", "1E", "SECONDS", uvw[:, 1] / 299792458.0),
        ("WW---SIN", "1E", "SECONDS", uvw[:, 2] / 299792458.0),
        ("DATE", "1D", "DAYS", np.full(n_row, jd0)),
        ("TIME", "1D", "DAYS", time_s / 86400.0 - mjd0),
        ("BASELINE", "1J", "", 256 * (a1 + 1) + a2 + 1), ("FILTER", "1J", "", np.zeros(n_row)),
        ("SOURCE_ID", "1J", "", np.ones(n_row)), ("FREQID", "1J", "", np.ones(n_row)),
        ("INTTIM", "1E", "SECONDS", np.ones(n_row)),
        ("WEIGHT", f"{n_st * nb}E", "", np.ones((n_row, n_st * nb))),
        ("FLUX", f"{2 * n_st * nb}E", "UNCALIB", flux.reshape(n_row, -1))],
        common + matrix + [("TMATX12", True), ("WEIGHTYP", "NORMAL"), ("SORT", "T*"),
                           ("DATE-OBS", rdate)], n_row)
    path.write_bytes(out)
    return path


def test_a_fitsidi_pair_comes_back_as_the_truth(tmp_path, shared_pair):
    from casacore import tables as pt

    truth = shared_pair(PairSpec(n_ant=4, n_time=200, seed=5, storage=Storage(time_order=True)))
    ref = write_fitsidi(tmp_path / "ref.idi", truth.ref_ms)
    tgt = write_fitsidi(tmp_path / "tgt.idi", truth.target_ms)
    assert convert.detect_format(ref) == "fitsidi"
    rep = calibrate_flat(ref, tgt, workdir=str(tmp_path / "w"), method="pwc", no_verdict=True)
    assert [c["tool"] for c in rep["conversions"]] == ["casatasks.importfitsidi"] * 2
    with pt.table(rep["target_ms"], ack=False) as t:
        pwc = t.getcol("PWC_DATA")[:, 0, :]
        key_out = np.round(t.getcol("TIME"), 3) * 1e3 + t.getcol("ANTENNA1") * 10 + t.getcol("ANTENNA2")
    key_in = np.round(truth.time, 3) * 1e3 + truth.ant1 * 10 + truth.ant2
    order_out, order_in = np.argsort(key_out), np.argsort(key_in)
    np.testing.assert_array_equal(key_out[order_out], key_in[order_in])
    expected = expected_pwc_phase(truth)[order_in]
    err = wrap(np.angle(pwc[order_out]) - expected)
    assert np.max(np.abs(err)) < 1e-4


def test_fitsidi_with_several_ifs_goes_in_as_several_windows(tmp_path, shared_pair):
    # four bands 2 GHz apart (the writer repeats the visibilities in each): four spectral
    # windows after importfitsidi, each calibrated by the reference band's one window;
    # band 0 is the truth's own frequency, so its PWC is the truth's
    from casacore import tables as pt

    truth = shared_pair(PairSpec(n_ant=3, n_time=20, storage=Storage(time_order=True)))  # only read
    ref = write_fitsidi(tmp_path / "ref.idi", truth.ref_ms)
    tgt = write_fitsidi(tmp_path / "four-ifs.idi", truth.target_ms, n_band=4)
    before = tgt.read_bytes()
    rep = calibrate_flat(ref, tgt, workdir=str(tmp_path / "w"), method="pwc", no_verdict=True)
    assert tgt.read_bytes() == before
    assert len(rep["groups"]) == 4
    with pt.table(rep["target_ms"], ack=False) as t:
        ddid = t.getcol("DATA_DESC_ID")
        pwc = t.getcol("PWC_DATA")[ddid == 0, 0, :]
        key_out = (np.round(t.getcol("TIME"), 3) * 1e3 + t.getcol("ANTENNA1") * 10
                   + t.getcol("ANTENNA2"))[ddid == 0]
    with pt.table(f"{rep['target_ms']}::SPECTRAL_WINDOW", ack=False) as t:
        assert t.nrows() == 4
    key_in = np.round(truth.time, 3) * 1e3 + truth.ant1 * 10 + truth.ant2
    order_out, order_in = np.argsort(key_out), np.argsort(key_in)
    np.testing.assert_array_equal(key_out[order_out], key_in[order_in])
    err = wrap(np.angle(pwc[order_out]) - expected_pwc_phase(truth)[order_in])
    assert np.max(np.abs(err)) < 1e-4
