"""hitops.io.uvfits: the exported UVFITS equals what CASA exportuvfits writes and reads back.

Three independent readers check the writer: astropy (the FITS structure and
every group parameter and visibility, compared with CASA exportuvfits of the
same set), CASA importuvfits (the values, flags and weights come back), and
the FITS header reader used for the input checks.  eht-imaging reads the files
in tests/test_interop_ehtim.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from hitops.testing import PairSpec, Signal, add_column
from hitops.errors import ColumnError, OutputExistsError
from hitops.io.fits import read_headers
from hitops.io.uvfits import export_uvfits


def _flagged_pair(new_pair, corr=("RR", "RL", "LR", "LL")):
    from casacore import tables as pt

    truth = new_pair(PairSpec(n_ant=4, n_time=30, dt=2.0, n_scans=3, corr_types=corr,
                              signal=Signal(sigma_target=0.1)))
    ms = str(truth.target_ms)
    rng = np.random.default_rng(2)
    with pt.table(ms, readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        flag[rng.random(flag.shape) < 0.05] = True
        t.putcol("FLAG", flag)
        flag_row = t.getcol("FLAG_ROW")
        flag_row[rng.random(flag_row.shape) < 0.03] = True
        t.putcol("FLAG_ROW", flag_row)
        weight = rng.uniform(0.5, 3.0, t.getcol("WEIGHT").shape).astype(np.float32)
        t.putcol("WEIGHT", weight)
        uvw = rng.normal(0, 3e6, (t.nrows(), 3))
        t.putcol("UVW", uvw)
    return truth, ms


def test_export_matches_casa_exportuvfits(tmp_path, new_pair):
    fits = pytest.importorskip("astropy.io.fits")
    from hitops.casa.runner import run_task

    _, ms = _flagged_pair(new_pair)
    ours = tmp_path / "ours.uvfits"
    summary = export_uvfits(ms, ours, "DATA")
    run_task("exportuvfits", vis=ms, fitsfile=str(tmp_path / "casa.uvfits"), datacolumn="data")
    with fits.open(ours) as a, fits.open(tmp_path / "casa.uvfits") as b:
        da, db = a[0].data, b[0].data
        # CASA drops rows with FLAG_ROW; everything else is the same, group by group
        d0 = float(db.par("DATE").min())
        key_a = np.round((da.par("DATE") - d0) * 86400).astype(np.int64) * 100000 + da.par("BASELINE").astype(np.int64)
        key_b = np.round((db.par("DATE") - d0) * 86400).astype(np.int64) * 100000 + db.par("BASELINE").astype(np.int64)
        common, ia, ib = np.intersect1d(key_a, key_b, return_indices=True)
        assert common.size == db.shape[0]
        for ours_name, casa_name in (("UU---SIN", "UU"), ("VV---SIN", "VV"), ("WW---SIN", "WW"),
                                     ("BASELINE", "BASELINE"), ("INTTIM", "INTTIM")):
            np.testing.assert_array_equal(da.par(ours_name)[ia], db.par(casa_name)[ib])
        assert np.max(np.abs(da.par("DATE")[ia] - db.par("DATE")[ib])) < 1e-7   # days
        np.testing.assert_array_equal(da.data[ia], db.data[ib])   # re, im, weight (<0 flagged)
        assert a[0].header["CRVAL3"] == b[0].header["CRVAL3"] == -1
        assert a[0].header["NAXIS3"] == b[0].header["NAXIS3"] == 4
        assert a[0].header["CRVAL4"] == b[0].header["CRVAL4"]
        np.testing.assert_array_equal(a["AIPS AN"].data["STABXYZ"], b["AIPS AN"].data["STABXYZ"])
        assert list(a["AIPS AN"].data["ANNAME"]) == ["AP", "SM", "PV", "GL"]
        assert len(a["AIPS NX"].data) == summary["scans"] == 3
        # rows flagged as a whole: every weight negative
        n_row_flagged = int(np.sum(np.all(da.data[..., 2] < 0, axis=tuple(range(1, 6)))))
        assert n_row_flagged >= da.shape[0] - db.shape[0]
    headers = read_headers(ours)
    assert [h.get("EXTNAME") for h, _, _ in headers] == [None, "AIPS AN", "AIPS FQ", "AIPS NX"]


def test_casa_importuvfits_reads_the_column_flags_and_weights_back(tmp_path, new_pair):
    from casacore import tables as pt

    from hitops.casa.runner import run_task

    truth, ms = _flagged_pair(new_pair)
    with pt.table(ms, ack=False) as t:
        data = t.getcol("DATA")
    pwc = data * np.exp(1j * 0.7)
    add_column(ms, "PWC_DATA", pwc)
    export_uvfits(ms, tmp_path / "pwc.uvfits", "PWC_DATA")
    run_task("importuvfits", fitsfile=str(tmp_path / "pwc.uvfits"), vis=str(tmp_path / "back.ms"))
    with pt.table(ms, ack=False) as t, pt.table(str(tmp_path / "back.ms"), ack=False) as b:
        def keyed(tab):
            k = np.round(tab.getcol("TIME"), 2) * 1e3 + tab.getcol("ANTENNA1") * 10 + tab.getcol("ANTENNA2")
            return np.argsort(k)
        o, r = keyed(t), keyed(b)
        flag_in = t.getcol("FLAG")[o] | t.getcol("FLAG_ROW")[o][:, None, None]
        np.testing.assert_array_equal(b.getcol("FLAG")[r], flag_in)
        np.testing.assert_allclose(b.getcol("DATA")[r], pwc[o].astype(np.complex64), atol=1e-6)
        np.testing.assert_allclose(b.getcol("WEIGHT")[r], t.getcol("WEIGHT")[o], rtol=1e-6)
        np.testing.assert_allclose(b.getcol("UVW")[r], t.getcol("UVW")[o], rtol=1e-6, atol=1e-3)
        np.testing.assert_allclose(b.getcol("TIME")[r], t.getcol("TIME")[o], atol=0.01)
    with pt.table(str(tmp_path / "back.ms") + "::ANTENNA", ack=False) as a:
        assert list(a.getcol("STATION")) == ["AP", "SM", "PV", "GL"]
    # the Measurement Set itself is untouched by the export (only read)
    with pt.table(ms, ack=False) as t:
        np.testing.assert_array_equal(t.getcol("DATA"), data)


def test_export_refuses_existing_files_and_missing_columns(tmp_path, new_pair):
    _, ms = _flagged_pair(new_pair, corr=("RR", "LL"))
    out = tmp_path / "x.uvfits"
    export_uvfits(ms, out, "DATA")
    before = out.read_bytes()
    with pytest.raises(OutputExistsError, match="pass --overwrite"):
        export_uvfits(ms, out, "DATA")
    assert out.read_bytes() == before
    with pytest.raises(ColumnError, match="no column PWC_DATA"):
        export_uvfits(ms, tmp_path / "y.uvfits", "PWC_DATA")
    assert not (tmp_path / "y.uvfits").exists()
    export_uvfits(ms, out, "DATA", overwrite=True)
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]


def test_header_reader_finds_truncation(tmp_path, new_pair):
    _, ms = _flagged_pair(new_pair, corr=("RR", "LL"))
    out = tmp_path / "x.uvfits"
    export_uvfits(ms, out, "DATA")
    raw = out.read_bytes()
    headers = read_headers(out)
    assert headers[0][0]["GROUPS"] is True and headers[0][0]["NAXIS1"] == 0
    cut = tmp_path / "cut.uvfits"
    cut.write_bytes(raw[:headers[0][1] + 1000])      # mid-data
    h = read_headers(cut)
    assert h[0][1] + h[0][2] > cut.stat().st_size   # the caller sees the data run past the end
    cut.write_bytes(raw[:headers[1][1] - 100])      # mid-header of the AN table
    with pytest.raises(ValueError, match="cut off"):
        read_headers(cut)
