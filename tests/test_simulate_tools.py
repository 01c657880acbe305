"""Simulated pairs through the real tools: CASA listobs/fringefit/gaincal, WSClean, casatools.simulator."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.simulate import simulate
from hitops.simulate.scene import load_scene_mapping

ROOT = Path(__file__).resolve().parent.parent

CASA_SCRIPT = r"""
import json, sys
from hitops.casa_env import ensure_casa_offline
ensure_casa_offline()
from casatasks import listobs, fringefit, gaincal
from casatools import table
ms86, ms230, work = sys.argv[1:4]
out = {}
for ms in (ms86, ms230):
    summary = listobs(vis=ms, listfile=f"{work}/listobs-{ms.split('/')[-1]}.txt", overwrite=True)
    text = open(f"{work}/listobs-{ms.split('/')[-1]}.txt").read()
    nrows = int(text.split("Data records:")[1].split()[0])
    scans = [line.split()[-7] for line in text.splitlines() if "[OBSERVE_TARGET" in line]
    out[ms] = {"nrows": nrows, "n_scan_lines": len(scans)}
fringefit(vis=ms230, caltable=f"{work}/ff.tbl", solint="20s", refant="PV,PB", minsnr=3)
gaincal(vis=ms230, caltable=f"{work}/sc.tbl", solint="10s", refant="PV,PB", calmode="p",
        gaintable=[f"{work}/ff.tbl"], minsnr=3)
tb = table()
for name in ("ff", "sc"):
    tb.open(f"{work}/{name}.tbl")
    flag = tb.getcol("FLAG")
    cols = tb.colnames()
    gains = tb.getcol("FPARAM" if "FPARAM" in cols else "CPARAM")
    out[name] = {"n": int(flag.size), "flagged": float(flag.mean()),
                 "ant": tb.getcol("ANTENNA1").tolist(), "time": tb.getcol("TIME").tolist(),
                 "phase": (gains[0, 0].tolist() if name == "ff" else
                           [float(__import__("cmath").phase(g)) for g in gains[0, 0]])}
    tb.close()
print("RESULT" + json.dumps(out))
"""


def demo_pair(tmp_path: Path, **overrides) -> dict:
    return simulate("demo", tmp_path, save_truth=True, **overrides)


@pytest.mark.slow
def test_casa_listobs_fringefit_gaincal_accept_the_pair(tmp_path):
    paths = demo_pair(tmp_path, duration=1200, scan_length=600, scan_gap=0)
    proc = subprocess.run([sys.executable, "-c", CASA_SCRIPT, str(paths["86"]), str(paths["230"]),
                           str(tmp_path)], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(proc.stdout.split("RESULT", 1)[1])
    for band in ("86", "230"):
        with pt.table(str(paths[band]), ack=False) as t:
            assert result[str(paths[band])]["nrows"] == t.nrows()
        assert result[str(paths[band])]["n_scan_lines"] == 2
    # fringefit and self-calibration found solutions on (nearly) every antenna and interval
    assert result["ff"]["n"] > 0 and result["ff"]["flagged"] < 0.1
    assert result["sc"]["n"] > 0 and result["sc"]["flagged"] < 0.1
    # ... and fringefit's phases follow the simulated troposphere: relative to the
    # reference antenna PV, the solved phase of AP tracks phi_AP - phi_PV (20 s means)
    truth = np.load(paths["truth"])
    stations = list(truth["stations"])
    p, ref = stations.index("AP"), stations.index("PV")
    true_rel = truth["phase_230"][p] - truth["phase_230"][ref]
    ff = result["ff"]
    sel = [i for i, a in enumerate(ff["ant"]) if a == p]
    times = np.array(ff["time"])[sel]
    solved = np.array(ff["phase"])[sel]
    expected = np.array([np.angle(np.mean(np.exp(1j * true_rel[np.abs(truth["time"] - t) <= 10])))
                         for t in times])
    resid = np.angle(np.exp(1j * (solved - expected)))
    # one constant offset at most (fringefit's phase reference), then agreement to ~0.3 rad
    resid = np.angle(np.exp(1j * (resid - np.angle(np.mean(np.exp(1j * resid))))))
    assert np.median(np.abs(resid)) < 0.3


def read_fits(path: Path):
    """Header cards and data of a simple FITS image (no astropy needed)."""
    raw = path.read_bytes()
    header, pos = {}, 0
    while True:
        block = raw[pos:pos + 2880].decode("ascii")
        pos += 2880
        cards = [block[i:i + 80] for i in range(0, 2880, 80)]
        for card in cards:
            if card[8:10] == "= ":
                header[card[:8].strip()] = card[10:].split("/")[0].strip().strip("'").strip()
        if any(c[:8].strip() == "END" for c in cards):
            break
    shape = [int(header[f"NAXIS{i}"]) for i in range(int(header["NAXIS"]), 0, -1)]
    data = np.frombuffer(raw[pos:pos + 4 * int(np.prod(shape))], dtype=">f4").reshape(shape)
    return header, data


def wsclean(ms: Path, name: str, work: Path, extra=()):
    cmd = ["wsclean", "-quiet", "-size", "128", "128", "-scale", "0.01masec", "-weight",
           "natural", "-name", str(work / name), *extra, str(ms)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=work)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


@pytest.mark.skipif(shutil.which("wsclean") is None, reason="wsclean not installed")
def test_wsclean_recovers_noise_free_point_source_flux(tmp_path):
    paths = simulate("demo", tmp_path, duration=1800, integration=10, no_noise=True,
                     no_troposphere=True)
    for band, flux in (("86", 1.1), ("230", 1.0)):
        wsclean(paths[band], f"img{band}", tmp_path, ["-niter", "200", "-mgain", "0.8",
                                                       "-gain", "0.2"])
        # the dirty image at the phase centre is the weighted mean visibility: the flux
        header, dirty = read_fits(tmp_path / f"img{band}-dirty.fits")
        centre = int(float(header["CRPIX2"])) - 1, int(float(header["CRPIX1"])) - 1
        assert np.unravel_index(np.argmax(dirty[0, 0]), dirty[0, 0].shape) == centre
        assert dirty[0, 0][centre] == pytest.approx(flux, rel=0.01)
        # CLEAN puts the flux in the centre pixel (sparse 4-station coverage: the
        # rest of the model is small sidelobe-chasing components)
        _, model = read_fits(tmp_path / f"img{band}-model.fits")
        assert model[0, 0][centre] == pytest.approx(flux, rel=0.01)
        assert np.abs(model[0, 0]).max() == model[0, 0][centre]


@pytest.mark.skipif(shutil.which("wsclean") is None, reason="wsclean not installed")
def test_wsclean_puts_an_offset_component_east_and_north(tmp_path):
    """The UVW sign and the model phase sign together give the right sky orientation."""
    scene, _ = load_scene_mapping("demo")
    scene["source"]["flux"] = {"86": 0.0, "230": 0.0}
    scene["source"]["components"] = [{"flux": {"86": 1.0, "230": 1.0}, "offset_ra": 300.0,
                                      "offset_dec": 150.0, "fwhm_major": 0.0}]
    scene["stations"] = ["AP", "SM", "PV", "PB", "KP", "GL"]
    scene["observation"].update({"start": "2023-04-10T01:00:00", "duration": 7200,
                                 "integration": 20})
    paths = simulate(scene, tmp_path, no_noise=True, no_troposphere=True)
    wsclean(paths["230"], "off", tmp_path, ["-niter", "0", "-size", "256", "256"])
    header, image = read_fits(tmp_path / "off-dirty.fits")
    iy, ix = np.unravel_index(np.argmax(image[0, 0]), image[0, 0].shape)
    cdelt_uas = abs(float(header["CDELT1"])) * 3.6e9
    east = -(ix + 1 - float(header["CRPIX1"])) * cdelt_uas      # RA grows to the left
    north = (iy + 1 - float(header["CRPIX2"])) * float(header["CDELT2"]) * 3.6e9
    assert east == pytest.approx(300.0, abs=cdelt_uas) and north == pytest.approx(150.0, abs=cdelt_uas)
    assert image[0, 0].max() == pytest.approx(1.0, rel=0.01)


@pytest.mark.slow
def test_uvw_sign_and_time_scale_against_casa_simulator(tmp_path):
    """casatools.simulator lays out the same rows: same UVW (its TIME label is TAI, +37 s)."""
    casa_ms = tmp_path / "casa.ms"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "casa_layout.py"), "demo",
                           str(casa_ms), "--band", "230", "--duration", "600",
                           "--integration", "1"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ours = simulate("demo", tmp_path / "ours", duration=600, integration=1, no_noise=True,
                    no_troposphere=True)
    with pt.table(str(casa_ms), ack=False) as t:
        c_time, c_a1, c_a2, c_uvw = (t.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "UVW"))
    with pt.table(str(ours["230"]), ack=False) as t:
        h_time, h_a1, h_a2, h_uvw = (t.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "UVW"))
    # CASA labels TAI as UTC: its TIME is ours + 37 s (leap seconds in 2023), GUIDE section 3
    assert c_time.min() - h_time.min() == pytest.approx(37.0, abs=1e-3)
    # its UVW are computed for the label read as UTC (not for the true instant 37 s
    # earlier), so rows with equal TIME labels must agree
    key = {(round(t, 3), a, b): i for i, (t, a, b) in enumerate(zip(h_time, h_a1, h_a2))}
    pairs = [(i, key[(round(t, 3), a, b)]) for i, (t, a, b) in enumerate(zip(c_time, c_a1, c_a2))
             if (round(t, 3), a, b) in key]
    assert len(pairs) > 100
    ci, hi = np.array(pairs).T
    diff = c_uvw[ci] - h_uvw[hi]
    # same sign convention; agreement to a few metres (CASA's own frame choices)
    assert np.abs(diff).max() < 20.0
    assert np.abs(c_uvw[ci] + h_uvw[hi]).max() > 1e5
