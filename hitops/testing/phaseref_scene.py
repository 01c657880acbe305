"""A phase-referencing pair whose truth is outside hitops: casatools.simulator lays it out.

CASA's simulator lays the rows out (antennas, UVW, scans of two fields with slews between
them, two 16 x 125 MHz windows at 86 and 229.1 GHz); the visibilities are then written
with numpy from the physics alone (no hitops code computes them):

* each line of sight (station x field) sees an excess path L(t) = a part shared by both
  fields plus a part of its own (the two lines part a few degrees apart, so the screen's
  larger scales are common and the smaller ones not); the troposphere is non-dispersive,
  so channel nu_k sees 2 pi nu_k L / c (GUIDE section 3, "Wideband");
* each station, band and hand has an instrumental phase and delay, both drifting
  linearly: theta(nu, t) = phi0 + phi1 t + 2 pi (nu - nu_c)(tau0 + tau1 t), nu_c the
  band's centre;
* the target is a point source of 1 Jy at its phase centre; the calibrator has two
  components (``calibrator_jy`` at its phase centre, ``companion_jy`` at ``companion_uas``), so it is
  resolved on these baselines, and its visibility is written to MODEL_DATA of both sets
  (1 on the target's rows, CASA's point-source default);
* V_pq = model_pq exp(i (theta_p - theta_q + 2 pi nu (L_p - L_q) / c)), the convention
  V_pq = g_p g_q^* of CASA's measurement equation; noise-free unless ``noise_jy``.

The temporal structure of L is Kolmogorov's (phase structure function (dt / t_c)^(5/3)
rad^2 at 230 GHz, generated as a power-law spectrum f^(-8/3) on a grid 4x the track).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

C_LIGHT = 299_792_458.0
TARGET = ("M87", "12h30m49.42s", "+12d23m28.04s")
#: 2.64 deg west of M87 (an ASSUMED calibrator position, not a catalogue source)
CALIBRATOR = ("CAL", "12h20m00.00s", "+12d23m28.04s")
CHAN_WIDTH_HZ = 125e6
UAS = np.pi / 180 / 3600e6


@dataclass(frozen=True)
class PhaserefSpec:
    """What the pair holds; every number a test may change."""

    slew_s: float = 60.0
    cal_scan_s: float = 60.0
    target_scan_s: float = 120.0
    duration_s: float = 1800.0
    integration_s: float = 4.0
    n_chan: int = 16
    ref_centre_hz: float = 86.0e9
    target_centre_hz: float = 229.1e9
    coherence_time_230_s: float = 10.0   # t_c of the shared path at 230 GHz
    own_fraction: float = 0.4            # the own part's rms against the shared part's
    phase_drift_deg_h: float = 30.0      # instrumental drifts per station, band and hand
    delay_drift_ns_h: float = 0.03
    companion_jy: float = 0.6            # the calibrator's second component
    companion_uas: Tuple[float, float] = (120.0, -80.0)   # its (l, m) offset
    calibrator_jy: float = 1.0           # the calibrator's central component
    noise_jy: float = 0.0                # thermal noise per visibility, real and imaginary
    seed: int = 7
    start_utc: str = "2023/04/10/03:00:00"
    #: four of the paper's stations that see M87 together at 03:00 UTC
    stations: Tuple[str, ...] = ("PV", "PB", "AP", "GL")

    def schedule(self) -> List[Tuple[str, float, float]]:
        """(field, start s, stop s): CAL, slew, TARGET, slew, ... ending with CAL."""
        scans, t = [], 0.0
        while t + self.cal_scan_s <= self.duration_s:
            scans.append((CALIBRATOR[0], t, t + self.cal_scan_s))
            t += self.cal_scan_s + self.slew_s
            if t + self.target_scan_s + self.slew_s + self.cal_scan_s > self.duration_s:
                break
            scans.append((TARGET[0], t, t + self.target_scan_s))
            t += self.target_scan_s + self.slew_s
        return scans


@dataclass(frozen=True)
class Instrument:
    """Per station, band and hand (n_ant, 2 bands, 2 hands): phase (rad), its drift (rad/s),
    delay (s) and its drift (s/s); band 0 the reference."""

    phase: np.ndarray
    phase_rate: np.ndarray
    delay: np.ndarray
    delay_rate: np.ndarray


@dataclass(frozen=True)
class PhaserefPair:
    """The two sets and the truth written into them."""

    ref_ms: Path
    target_ms: Path
    spec: PhaserefSpec
    times: np.ndarray                 # (n_time,) distinct MS TIME
    path_m: Dict[str, np.ndarray] = field(default_factory=dict)   # field -> (n_time, n_ant)
    instrument: Instrument = None


def station_positions(codes) -> np.ndarray:
    """(n, 3) ITRF metres of ``codes`` from the package's station catalogue
    (hitops/scenes/stations.yml: public EHT station lists, GUIDE section 2)."""
    import importlib.resources

    import yaml

    text = importlib.resources.files("hitops.scenes").joinpath("stations.yml").read_text()
    catalogue = yaml.safe_load(text)
    return np.array([catalogue[code]["itrf"] for code in codes], float)


def lay_out(ms: Path, centre_hz: float, spec: PhaserefSpec) -> None:
    """An empty set laid out by casatools.simulator, in a process of its own (its observe
    has crashed inside a pytest process that ran other CASA tools: tests/solutions_scene.py)."""
    args = {"ms": str(ms), "centre_hz": centre_hz, "n_chan": spec.n_chan,
            "scans": spec.schedule(), "start_utc": spec.start_utc,
            "stations": list(spec.stations), "integration_s": spec.integration_s}
    proc = subprocess.run([sys.executable, "-m", "hitops.testing.phaseref_scene",
                           json.dumps(args)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"casatools.simulator could not lay out {ms} (exit "
                           f"{proc.returncode}):\n{proc.stderr[-3000:]}")


def _lay_out_here(ms: str, centre_hz: float, n_chan: int, scans, start_utc: str,
                  stations, integration_s: float) -> None:
    from hitops.casa_env import ensure_casa_offline

    ensure_casa_offline()
    from casatools import measures, simulator

    me, sm = measures(), simulator()
    shutil.rmtree(ms, ignore_errors=True)
    xyz = station_positions(stations)
    sm.open(ms)
    sm.setconfig(telescopename="EHT", x=xyz[:, 0].tolist(), y=xyz[:, 1].tolist(),
                 z=xyz[:, 2].tolist(), dishdiameter=[12.0] * len(stations),
                 mount=["alt-az"] * len(stations), antname=list(stations),
                 padname=list(stations), coordsystem="global",
                 referencelocation=me.position("ITRF", *(f"{v}m" for v in xyz[0])))
    first = centre_hz - (n_chan - 1) / 2 * CHAN_WIDTH_HZ
    sm.setspwindow(spwname="spw0", freq=f"{first}Hz", deltafreq=f"{CHAN_WIDTH_HZ}Hz",
                   freqresolution=f"{CHAN_WIDTH_HZ}Hz", nchannels=n_chan, stokes="RR LL")
    sm.setfeed(mode="perfect R L")
    for name, ra, dec in (TARGET, CALIBRATOR):
        sm.setfield(sourcename=name, sourcedirection=me.direction("J2000", ra, dec))
    sm.setlimits(shadowlimit=0.001, elevationlimit="0deg")
    sm.setauto(autocorrwt=0.0)
    sm.settimes(integrationtime=f"{integration_s}s", usehourangle=False,
                referencetime=me.epoch("UTC", start_utc))
    for name, start, stop in scans:
        sm.observe(sourcename=name, spwname="spw0", starttime=f"{start}s", stoptime=f"{stop}s")
    sm.close()
    sm.done()


def kolmogorov_phase(n: int, dt: float, coherence_time_s: float,
                     rng: np.random.Generator) -> np.ndarray:
    """A phase series (rad) with structure function (tau / t_c)^(5/3): a power spectrum
    f^(-8/3) drawn on a grid 4x longer (so the track does not wrap round), scaled so
    that the series' own structure function at tau = t_c is 1 rad^2."""
    m = 4 * n
    freq = np.fft.rfftfreq(m, dt)
    amp = np.zeros(freq.size)
    amp[1:] = freq[1:] ** (-8.0 / 6.0)
    spec = amp * (rng.normal(size=freq.size) + 1j * rng.normal(size=freq.size))
    series = np.fft.irfft(spec, m)
    lag = max(1, int(round(coherence_time_s / dt)))
    d_at_tc = np.mean((series[lag:] - series[:-lag]) ** 2)
    start = rng.integers(0, m - n)
    return series[start:start + n] / np.sqrt(d_at_tc)


def excess_paths(spec: PhaserefSpec, times: np.ndarray,
                 rng: np.random.Generator) -> Dict[str, np.ndarray]:
    """field -> (n_time, n_ant) path (m): a shared part plus ``own_fraction`` of one of
    its own per station and field (the own part with the same t_c: a smaller amplitude
    at the same speed is what a few degrees of separation through one screen gives)."""
    dt = float(np.median(np.diff(times)))
    grid = np.arange(times[0], times[-1] + dt / 2, dt)
    metres_per_rad = C_LIGHT / (2 * np.pi * 230e9)
    n_ant = len(spec.stations)

    def draw() -> np.ndarray:
        series = np.stack([kolmogorov_phase(grid.size, dt, spec.coherence_time_230_s, rng)
                           for _ in range(n_ant)], axis=1) * metres_per_rad
        return np.stack([np.interp(times, grid, series[:, a]) for a in range(n_ant)], axis=1)

    shared = draw()
    return {name: shared + spec.own_fraction * draw() for name in (TARGET[0], CALIBRATOR[0])}


def draw_instrument(n_ant: int, rng: np.random.Generator, phase_drift_deg_h: float,
                    delay_drift_ns_h: float) -> Instrument:
    """ASSUMED instrumental terms (what is left after correlation once the clock, common
    to both bands, is gone): any phase, delays within +-0.4 ns, drifts up to
    ``phase_drift_deg_h`` and ``delay_drift_ns_h``; the hands share the delay and differ
    in phase."""
    shape = (n_ant, 2, 2)
    hour = 3600.0
    delay = np.repeat(rng.uniform(-0.4e-9, 0.4e-9, (n_ant, 2, 1)), 2, axis=2)
    delay_rate = np.repeat(rng.uniform(-1, 1, (n_ant, 2, 1)), 2, axis=2) * delay_drift_ns_h * 1e-9 / hour
    return Instrument(phase=rng.uniform(-np.pi, np.pi, shape),
                      phase_rate=np.radians(rng.uniform(-1, 1, shape) * phase_drift_deg_h) / hour,
                      delay=delay, delay_rate=delay_rate)


def calibrator_model(uvw: np.ndarray, chan_freq: np.ndarray, spec: PhaserefSpec) -> np.ndarray:
    """(n_row, n_chan) visibility of the two-component calibrator (CASA's sign:
    exp(-2 pi i (u l + v m) nu / c))."""
    l_off, m_off = (x * UAS for x in spec.companion_uas)
    geometric = (uvw[:, 0:1] * l_off + uvw[:, 1:2] * m_off) * chan_freq[None, :] / C_LIGHT
    return spec.calibrator_jy + spec.companion_jy * np.exp(-2j * np.pi * geometric)


def write_visibilities(ms: Path, band: int, centre_hz: float, pair: PhaserefPair) -> None:
    """DATA, MODEL_DATA and FLAG of one set from the pair's truth (see the module's text)."""
    from casacore import tables as pt

    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        chan_freq = t.getcol("CHAN_FREQ")[0]
    with pt.table(f"{ms}::FIELD", ack=False) as t:
        field_names = list(t.getcol("NAME"))
    inst = pair.instrument
    with pt.table(str(ms), readonly=False, ack=False) as t:
        time = t.getcol("TIME")
        it = np.searchsorted(pair.times, time)
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        fld = np.array(field_names)[t.getcol("FIELD_ID")]
        elapsed = (time - pair.times[0])[:, None]
        offset = (chan_freq - centre_hz)[None, :]
        data = np.zeros((time.size, chan_freq.size, 2), np.complex128)
        model = np.ones_like(data)
        path = np.zeros(time.size)
        for name, series in pair.path_m.items():
            rows = fld == name
            path[rows] = series[it[rows], a1[rows]] - series[it[rows], a2[rows]]
        cal = fld == CALIBRATOR[0]
        sky = calibrator_model(t.getcol("UVW")[cal], chan_freq, pair.spec)
        for hand in range(2):
            def theta(ant):
                phase = inst.phase[ant, band, hand][:, None] + inst.phase_rate[ant, band, hand][:, None] * elapsed
                delay = inst.delay[ant, band, hand][:, None] + inst.delay_rate[ant, band, hand][:, None] * elapsed
                return phase + 2 * np.pi * offset * delay
            tropo = 2 * np.pi * chan_freq[None, :] * path[:, None] / C_LIGHT
            data[:, :, hand] = np.exp(1j * (theta(a1) - theta(a2) + tropo))
            model[cal, :, hand] = sky
        vis = data * model
        if pair.spec.noise_jy > 0:
            noise = np.random.default_rng(pair.spec.seed + 1000 * (band + 1))
            vis = vis + pair.spec.noise_jy * (noise.normal(size=vis.shape)
                                              + 1j * noise.normal(size=vis.shape))
        t.putcol("DATA", vis.astype(np.complex64))
        t.putcol("MODEL_DATA", model.astype(np.complex64))
        t.putcol("FLAG", np.zeros(data.shape, bool))


def make_phaseref_pair(workdir: Path, spec: PhaserefSpec = PhaserefSpec()) -> PhaserefPair:
    """Lay out both sets and write the truth into them: ref.ms (86 GHz), target.ms."""
    from casacore import tables as pt

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = workdir / "ref.ms", workdir / "target.ms"
    lay_out(ref_ms, spec.ref_centre_hz, spec)
    lay_out(target_ms, spec.target_centre_hz, spec)
    with pt.table(str(ref_ms), ack=False) as t:
        times = np.unique(t.getcol("TIME"))
    rng = np.random.default_rng(spec.seed)
    pair = PhaserefPair(ref_ms, target_ms, spec, times, excess_paths(spec, times, rng),
                        draw_instrument(len(spec.stations), rng, spec.phase_drift_deg_h,
                                        spec.delay_drift_ns_h))
    write_visibilities(ref_ms, 0, spec.ref_centre_hz, pair)
    write_visibilities(target_ms, 1, spec.target_centre_hz, pair)
    return pair


if __name__ == "__main__":   # lay_out's own process
    _lay_out_here(**json.loads(sys.argv[1]))


def target_coherence(ms: Path, column: str) -> np.ndarray:
    """Whole-track coherence |mean V / |V|| of the target field per baseline, channel and
    hand (n_bl, n_chan, n_corr); unflagged samples only (a series wholly flagged: 0)."""
    from casacore import tables as pt

    with pt.table(f"{ms}::FIELD", ack=False) as t:
        target_id = list(t.getcol("NAME")).index(TARGET[0])
    with pt.table(str(ms), ack=False) as t:
        rows = np.flatnonzero(t.getcol("FIELD_ID") == target_id)
        a1, a2 = t.getcol("ANTENNA1")[rows], t.getcol("ANTENNA2")[rows]
        data, flag = t.getcol(column)[rows], t.getcol("FLAG")[rows]
    unit = np.where(flag | (np.abs(data) == 0), 0, data / np.maximum(np.abs(data), 1e-30))
    out = []
    for p, q in sorted(set(zip(a1.tolist(), a2.tolist()))):
        mine = (a1 == p) & (a2 == q)
        out.append(np.abs(unit[mine].sum(axis=0)) / mine.sum())
    return np.array(out)


def one_integer_per_baseline(monkeypatch) -> None:
    """The plausible wrong calibrator step for tests: every scan's integer taken to be the
    first's (one per baseline for the whole track), on the calibrator and the target;
    ``monkeypatch``: pytest's, which undoes it after the test."""
    from hitops.calibrate.phaseref import apply as target_side
    from hitops.calibrate.phaseref import solve as calibrator_side

    found = target_side.target_integers

    def first_only(times, sums, counts, frame):
        shape = (sums.shape[0], sums.shape[1], sums.shape[3])
        return calibrator_side.CalibratorIntegers(np.zeros(shape, np.int64),
                                                  np.full(shape, np.nan), "first")

    def none_on_target(*args):
        out = found(*args)
        return target_side.TargetIntegers(out.scans, out.baselines, 0 * out.integers,
                                          out.margin, out.valid)

    monkeypatch.setattr(calibrator_side, "calibrator_integers", first_only)
    monkeypatch.setattr(target_side, "target_integers", none_on_target)
