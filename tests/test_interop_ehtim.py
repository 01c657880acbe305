"""eht-imaging reads what hitops writes, and hitops calibrates what eht-imaging writes.

* Output: a noise-free point-source scene (hitops simulate, 5 stations, scans
  with gaps) calibrated with the antenna tracker and exported with
  ``--export-uvfits`` is loaded by eht-imaging; on every baseline the RR and
  LL phase coherence |mean(V/|V|)| over each scan is at least 0.999 and the
  closure phases average to 0 within 0.1 deg (computed from ``obs.data``:
  ehtim's own ``c_phases`` fails with current numpy).
* Input: a pair written by eht-imaging (``Array.obsdata`` + ``save_uvfits``;
  its ``Model.observe`` fails with current numpy, so the point source and a
  shared troposphere are put into ``obs.data`` directly) goes into
  ``hitops calibrate`` as UVFITS and the truth comes back: PWC is constant on
  every baseline and scan and sits on the 2*pi*eps*k lattice, while CFPT jumps.

Skipped when eht-imaging (pip ``ehtim``, the ``ehtim`` extra) is not installed.
"""

from __future__ import annotations

import math
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

eh = pytest.importorskip("ehtim")

from hitops.calibrate import calibrate_flat  # noqa: E402

R = 230.0 / 86.0
EPS = R - math.floor(R)


def load(path):
    return eh.obsdata.load_uvfits(str(path), polrep="circ")


def scans_of(obs):
    """Scan index of every row: from the NX table eht-imaging read, else time gaps."""
    t = obs.data["time"]
    if obs.scans is not None and len(obs.scans):
        edges = np.asarray(obs.scans)
        idx = np.full(t.size, -1)
        for k, (a, b) in enumerate(edges):
            idx[(t >= a - 1e-6) & (t <= b + 1e-6)] = k
        assert np.all(idx >= 0), "rows outside every NX scan"
        return idx
    ut = np.unique(t)
    gaps = np.diff(ut) * 3600 > 30
    return np.searchsorted(ut[1:][gaps], t, side="right")


def coherence_per_scan(obs, field):
    """{(t1, t2, scan): |mean(V/|V|)|} over the unflagged samples of each baseline and scan."""
    scan = scans_of(obs)
    vis = obs.data[field]
    out = {}
    for key in set(zip(obs.data["t1"], obs.data["t2"], scan)):
        sel = ((obs.data["t1"] == key[0]) & (obs.data["t2"] == key[1]) & (scan == key[2])
               & np.isfinite(vis) & (np.abs(vis) > 0))
        if sel.sum() >= 2:
            v = vis[sel]
            out[key] = float(np.abs(np.mean(v / np.abs(v))))
    return out


def closure_phases(obs, field):
    """{triangle: closure phases (rad) at every time all three baselines are present}."""
    vis = {}
    for row in obs.data:
        v = row[field]
        if np.isfinite(v) and abs(v) > 0:
            vis[(row["time"], row["t1"], row["t2"])] = v
            vis[(row["time"], row["t2"], row["t1"])] = np.conj(v)
    sites = sorted(set(obs.data["t1"]) | set(obs.data["t2"]))
    times = np.unique(obs.data["time"])
    out = {}
    for a, b, c in combinations(sites, 3):
        phases = [np.angle(vis[(t, a, b)] * vis[(t, b, c)] * vis[(t, c, a)]) for t in times
                  if (t, a, b) in vis and (t, b, c) in vis and (t, c, a) in vis]
        if phases:
            out[(a, b, c)] = np.asarray(phases)
    return out


@pytest.fixture(scope="module")
def point_source(tmp_path_factory):
    """Noise-free point source, antenna tracker, exported as UVFITS."""
    from hitops.simulate import simulate

    work = tmp_path_factory.mktemp("ehtim-out")
    sets = simulate("demo", work, duration=1800, scan_length=300, scan_gap=60, no_noise=True)
    out = work / "pwc.uvfits"
    report = calibrate_flat(sets["86"], sets["230"], method="pwc", tracker="antenna",
                       export_uvfits=str(out), no_verdict=True)
    return work, sets, out, report


def test_ehtim_loads_the_export_coherent_per_scan(point_source):
    _, _, out, report = point_source
    assert report["export_uvfits"]["column"] == "PWC_DATA"
    obs = load(out)
    assert obs.scans is not None and len(obs.scans) == report["export_uvfits"]["scans"] >= 5
    n_bl = len(set(zip(obs.data["t1"], obs.data["t2"])))
    assert n_bl == 10
    for field in ("rrvis", "llvis"):
        coh = coherence_per_scan(obs, field)
        assert len(coh) >= n_bl * 5
        worst = min(coh, key=coh.get)
        assert coh[worst] >= 0.999, f"{field} {worst}: coherence {coh[worst]:.5f}"
    # the uncalibrated band is not coherent: the test would notice a no-op
    raw = coherence_per_scan(load(_raw_export(point_source)), "rrvis")
    assert min(raw.values()) < 0.9


def _raw_export(point_source):
    from hitops.io.uvfits import export_uvfits

    work, sets, _, _ = point_source
    raw = work / "raw.uvfits"
    if not raw.exists():
        export_uvfits(sets["230"], raw, "DATA")
    return raw


def test_ehtim_closure_phases_of_the_export_are_zero(point_source):
    _, _, out, _ = point_source
    obs = load(out)
    for field in ("rrvis", "llvis"):
        closures = closure_phases(obs, field)
        assert len(closures) == 10            # every triangle of 5 stations
        for tri, phases in closures.items():
            mean = math.degrees(np.angle(np.mean(np.exp(1j * phases))))
            assert abs(mean) < 0.1, f"{field} {tri}: mean closure {mean:.3f} deg"
            assert abs(math.degrees(np.mean(phases))) < 0.1


@pytest.fixture(scope="module")
def ehtim_pair(tmp_path_factory):
    """86 and 230 GHz UVFITS written by eht-imaging: point source, shared troposphere, scans."""
    from hitops.simulate.scene import parse_scene

    work = tmp_path_factory.mktemp("ehtim-in")
    scene = parse_scene("demo")
    dtype = eh.const_def.DTARR
    tarr = np.array([(s.code, *s.itrf, 5000.0, 5000.0, 0j, 0j, 0.0, 0.0, 0.0)
                     for s in scene.stations], dtype=dtype)
    array = eh.array.Array(tarr)
    ra_h, dec_deg = 12.5137278, 12.3911222

    def observe(rf):
        return array.obsdata(ra_h, dec_deg, rf, 2e9, 10.0, 10.0, 1.0, 4.0, mjd=60044,
                             elevmin=0.0, elevmax=90.0)

    o86, o230 = observe(86e9), observe(230e9)
    assert np.array_equal(o86.data["time"], o230.data["time"])
    times = np.unique(o86.data["time"])
    # five 25-minute scans with 11-minute gaps (rows kept in both bands alike)
    keep_t = ((times - times[0]) * 60.0) % 36.0 < 25.0
    keep = np.isin(o86.data["time"], times[keep_t])
    o86.data, o230.data = o86.data[keep], o230.data[keep]
    sites = [str(s) for s in tarr["site"]]
    rng = np.random.default_rng(17)
    n_t = times.size
    phase = (np.cumsum(rng.normal(0.0, 0.25, (len(sites), n_t)), axis=1)
             + np.linspace(-0.12, 0.12, len(sites))[:, None] * np.arange(n_t))
    it = np.searchsorted(times, o86.data["time"])
    p = np.array([sites.index(s) for s in o86.data["t1"]])
    q = np.array([sites.index(s) for s in o86.data["t2"]])
    tropo = phase[p, it] - phase[q, it]        # non-dispersive: R times it at 230 GHz
    o86.data["vis"] = 1.1 * np.exp(1j * tropo)
    o230.data["vis"] = 1.0 * np.exp(1j * R * tropo)
    for o in (o86, o230):
        o.data["sigma"] = 0.01
        o.source = "M87"
    ref, tgt = work / "ehtim-86.uvfits", work / "ehtim-230.uvfits"
    o86.save_uvfits(str(ref))
    o230.save_uvfits(str(tgt))
    return work, ref, tgt


@pytest.mark.parametrize("tracker", ["count", "antenna"])
def test_a_pair_written_by_ehtim_comes_back_as_the_truth(ehtim_pair, tracker):
    from casacore import tables as pt

    work, ref, tgt = ehtim_pair
    rep = calibrate_flat(ref, tgt, workdir=str(work / tracker), method="pwc,cfpt", tracker=tracker,
                    no_verdict=True, overwrite=True)
    assert [c["format"] for c in rep["conversions"]] == ["uvfits", "uvfits"]
    assert rep["conversions"][1]["n_scans"] == 5
    assert abs(rep["ratio"] - R) < 1e-9
    ms = rep["target_ms"]
    with pt.table(ms, ack=False) as t:
        pwc = t.getcol("PWC_DATA")[:, 0, :]
        cfpt = t.getcol("CFPT_DATA")[:, 0, :]
        flag = t.getcol("FLAG")[:, 0, :]
        key = t.getcol("ANTENNA1") * 100 + t.getcol("ANTENNA2")
        scan = t.getcol("SCAN_NUMBER")
    with pt.table(f"{ms}::POLARIZATION", ack=False) as t:
        corr = list(t.getcol("CORR_TYPE")[0])
    n_wraps = sum(w["wrap_events"] for w in rep["wraps"])
    assert n_wraps > 20                          # the troposphere did wrap at 86 GHz
    lattice = 2 * np.pi * EPS * np.arange(-60, 61)
    cfpt_jumps = 0
    for c, code in enumerate(corr):
        if code not in (5, 8):                   # RL, LR hold zeros in ehtim's files
            continue
        for k in np.unique(key):
            for s in np.unique(scan):
                sel = (key == k) & (scan == s) & ~flag[:, c]
                if sel.sum() < 2:
                    continue
                phase = np.angle(pwc[sel, c])
                # constant over the scan ...
                assert np.abs(np.mean(np.exp(1j * phase))) > 0.99999
                # ... and a multiple of 2*pi*eps (the n0 constants of the tracker)
                dist = np.abs(np.angle(np.exp(1j * (phase[0] - lattice))))
                assert dist.min() < 1e-3, f"PWC phase {phase[0]:.4f} is off the 2 pi eps lattice"
                cfpt_jumps += np.abs(np.mean(np.exp(1j * np.angle(cfpt[sel, c])))) < 0.99
    assert cfpt_jumps > 0                        # CFPT keeps the 2 pi eps jumps
    if tracker == "antenna":
        # antenna-based n0: closure phases of the output are zero
        _closures_zero(ms)


def _closures_zero(ms):
    from casacore import tables as pt

    with pt.table(ms, ack=False) as t:
        pwc = t.getcol("PWC_DATA")[:, 0, 0]
        flag = t.getcol("FLAG")[:, 0, 0]
        a1, a2, tm = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), np.round(t.getcol("TIME"), 1)
    vis = {(tt, p, q): v for tt, p, q, v, f in zip(tm, a1, a2, pwc, flag) if not f}
    vis.update({(tt, q, p): np.conj(v) for (tt, p, q), v in list(vis.items())})
    worst = 0.0
    for (tt, p, q), v in vis.items():
        for r in range(8):
            if p < q < r and (tt, q, r) in vis and (tt, r, p) in vis:
                worst = max(worst, abs(np.angle(v * vis[(tt, q, r)] * vis[(tt, r, p)])))
    assert math.degrees(worst) < 0.01


# ------------------------------------------------------------- several IFs
# eht-imaging 1.3.2's load_uvfits (ehtim/io/load.py, load_obs_uvfits) reads CRVAL4/CDELT4/NAXIS4
# and NAXIS5 but no FQ table.  It averages the IFs and channels it is given coherently into one
# visibility per row (weighted by the file's weights), puts that average at rf = the AN table's
# FREQ (our first IF's first channel) for u and v, and reports bw = n_if * n_chan * CDELT4.
# With several IFs *and* several channels its default (IF=all, channel=all) stops with an
# IndexError (it indexes DATA with the two lists together, which numpy broadcasts); one IF at a
# time (IF=[i]: that IF's channels averaged) or one channel (channel=[k]) loads.  The truth comes
# from the path written into a casatools.simulator layout (tests/solutions_scene.py).


@pytest.fixture(scope="module")
def wideband_export(tmp_path_factory):
    """The wideband pair's target exported raw (two IFs of 16 channels) and after PWC."""
    from casacore import tables as pt

    from hitops.io.uvfits import export_uvfits
    from solutions_scene import make_solution_pair

    work = tmp_path_factory.mktemp("ehtim-ifs")
    pair = make_solution_pair(work)
    raw = work / "raw.uvfits"
    export_uvfits(pair.target_ms, raw)
    pwc = work / "pwc.uvfits"
    calibrate_flat(str(pair.ref_ms), str(pair.target_ms), method="pwc", tracker="antenna",
              offset_model="point", export_uvfits=str(pwc), no_verdict=True)
    with pt.table(f"{pair.target_ms}::SPECTRAL_WINDOW", ack=False) as t:
        chan_freq = t.getcol("CHAN_FREQ")                    # (n_if, n_chan)
    hours = (pair.times - 86400.0 * np.floor(pair.times[0] / 86400.0)) / 3600.0
    return raw, pwc, chan_freq, (hours, pair.path_m)


def _truth(obs, paths, freq):
    """The written visibility exp(2 pi i nu (L_p - L_q) / c) of every ehtim row at ``freq``
    (scalar, or (n,) averaged coherently)."""
    hours, path_m = paths
    names = list(obs.tarr["site"])
    # ehtim's times come from float32 day fractions (ms): the nearest 1-s integration
    it = np.clip(np.searchsorted(hours, obs.data["time"]), 1, hours.size - 1)
    it = np.where(np.abs(hours[it - 1] - obs.data["time"]) < np.abs(hours[it] - obs.data["time"]),
                  it - 1, it)
    assert np.abs(hours[it] - obs.data["time"]).max() * 3600 < 0.1
    p = np.array([names.index(a) for a in obs.data["t1"]])
    q = np.array([names.index(b) for b in obs.data["t2"]])
    delta = path_m[it, p] - path_m[it, q]
    freq = np.atleast_1d(np.asarray(freq, np.float64))
    return np.exp(2j * np.pi * np.outer(delta, freq) / 299792458.0).mean(axis=1)


def test_ehtim_reads_every_if_and_channel_of_a_multi_if_export(wideband_export):
    raw, _, chan_freq, paths = wideband_export
    n_if, n_chan = chan_freq.shape
    assert (n_if, n_chan) == (2, 16)
    worst = 0.0
    for i in range(n_if):
        for k in (0, 7, 15):
            obs = eh.obsdata.load_uvfits(str(raw), polrep="circ", IF=[i], channel=[k])
            assert len(obs.data) == 6 * 1200
            truth = _truth(obs, paths, chan_freq[i, k])
            for field in ("rrvis", "llvis"):
                worst = max(worst, float(np.abs(np.angle(obs.data[field] * np.conj(truth))).max()))
    assert worst < 1e-4          # each IF's channel k is that window's channel k


def test_ehtim_averages_one_if_at_a_time_coherently(wideband_export):
    raw, pwc, chan_freq, paths = wideband_export
    with pytest.raises(IndexError):           # the default, every IF and channel at once
        eh.obsdata.load_uvfits(str(raw), polrep="circ")
    for i in range(chan_freq.shape[0]):
        obs = eh.obsdata.load_uvfits(str(raw), polrep="circ", IF=[i])
        assert obs.rf == pytest.approx(chan_freq[0, 0], rel=1e-12)     # IF 1's first channel
        assert obs.bw == pytest.approx(2 * 16 * 125e6, rel=1e-12)
        truth = _truth(obs, paths, chan_freq[i])        # the mean over the IF's 16 channels
        assert np.abs(obs.data["rrvis"] - truth).max() < 1e-5
        assert np.abs(truth).min() < 0.99               # raw: the window decorrelates
        # after PWC every channel is flat, so the average keeps the amplitude
        calibrated = eh.obsdata.load_uvfits(str(pwc), polrep="circ", IF=[i])
        for field in ("rrvis", "llvis"):
            vis = calibrated.data[field]
            assert np.abs(vis).min() >= 0.999
            assert np.abs(np.angle(vis)).max() < 1e-2
