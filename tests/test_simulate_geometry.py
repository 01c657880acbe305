"""UVW and elevations of simulated Measurement Sets against python-casacore measures."""

from __future__ import annotations

import numpy as np
import pytest
from casacore import quanta as qa
from casacore import tables as pt
from casacore.measures import measures

from hitops.simulate import simulate
from hitops.simulate.geometry import earth_rotation_angle, time_grid


@pytest.fixture(scope="module")
def paper_track(tmp_path_factory):
    """The paper's 8 stations over 12 h at 2-minute integrations, no corruption."""
    out = tmp_path_factory.mktemp("geom")
    paths = simulate("paper", out, integration=120, no_noise=True, no_troposphere=True,
                     save_truth=True)
    with pt.table(str(paths["230"]), ack=False) as t:
        cols = {c: t.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "UVW")}
    with pt.table(f"{paths['230']}::ANTENNA", ack=False) as t:
        cols["POSITION"] = t.getcol("POSITION")
    with pt.table(f"{paths['230']}::FIELD", ack=False) as t:
        cols["PHASE_DIR"] = t.getcol("PHASE_DIR")[0, 0]
    return cols, np.load(paths["truth"])


def casacore_uvw(time, pos1, pos2, ra, dec, reference):
    """UVW (m) of baseline pos1 - pos2 from casacore measures, J2000 (the MS convention used).

    casacore's to_uvw depends on the frame position at the ~20 m level on
    10^4 km baselines (it applies the observer's aberration), so the frame is
    the array reference position the simulator uses: the first station.
    """
    dm = measures()
    dm.do_frame(dm.position("ITRF", *[qa.quantity(float(x), "m") for x in reference]))
    dm.do_frame(dm.direction("J2000", qa.quantity(ra, "rad"), qa.quantity(dec, "rad")))
    dm.do_frame(dm.epoch("UTC", qa.quantity(float(time), "s")))
    b = pos1 - pos2
    baseline = dm.baseline("ITRF", *[qa.quantity(float(x), "m") for x in b])
    return np.asarray(dm.to_uvw(baseline)["xyz"].get_value("m"))


def test_uvw_agrees_with_casacore_measures(paper_track):
    cols, _ = paper_track
    ra, dec = cols["PHASE_DIR"]
    rows = np.linspace(0, cols["TIME"].size - 1, 150).astype(int)
    pos = cols["POSITION"]
    err = np.array([cols["UVW"][r] - casacore_uvw(cols["TIME"][r], pos[cols["ANTENNA1"][r]],
                                                  pos[cols["ANTENNA2"][r]], ra, dec, pos[0])
                    for r in rows])
    lengths = np.linalg.norm(cols["UVW"][rows], axis=1)
    assert lengths.max() > 9e6                     # intercontinental baselines are in the sample
    # millimetre agreement on 10^4 km baselines.  Single casacore evaluations
    # scatter by ~0.7 mm rms around their own smooth trend (depending on the
    # call history of its measures caches), which bounds any comparison.
    assert np.sqrt(np.mean(err ** 2)) < 1e-3
    assert np.median(np.abs(err)) < 0.5e-3
    assert np.abs(err).max() < 5e-3


def test_elevations_agree_with_casacore_azelgeo(paper_track):
    cols, truth = paper_track
    ra, dec = cols["PHASE_DIR"]
    dm = measures()
    source = dm.direction("J2000", qa.quantity(ra, "rad"), qa.quantity(dec, "rad"))
    for s in (0, 2, 6):
        pos = cols["POSITION"][s]
        dm.do_frame(dm.position("ITRF", *[qa.quantity(float(x), "m") for x in pos]))
        for it in (10, 150, 300):
            dm.do_frame(dm.epoch("UTC", qa.quantity(float(truth["time"][it]), "s")))
            el = dm.measure(source, "AZELGEO")["m1"]["value"]    # geodetic zenith, as ours
            # no refraction or diurnal aberration in ours: arcsecond-level agreement
            assert truth["elevation"][s, it] == pytest.approx(el, abs=np.radians(20 / 3600))


def test_earth_rotation_angle_rate():
    t = np.array([0.0, 86400.0]) + 5.1878016e9
    turns = np.diff(np.unwrap(earth_rotation_angle(t)))[0] / (2 * np.pi)
    assert turns % 1.0 == pytest.approx(0.00273781191135448, abs=1e-9)


def test_time_grid_scans():
    centres, scan, on = time_grid(0.0, 100.0, 10.0, scan_length=30.0, scan_gap=20.0)
    assert list(centres) == [5, 15, 25, 35, 45, 55, 65, 75, 85, 95]
    assert list(on) == [True, True, True, False, False, True, True, True, False, False]
    assert list(scan) == [1, 1, 1, 1, 1, 2, 2, 2, 2, 2]
