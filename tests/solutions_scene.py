"""A noise-free multi-channel reference/target pair laid out by casatools.simulator.

CASA's own simulator lays the rows out (antennas, UVW, times, windows), so the
truth the solution-space tests check against comes from outside hitops.  The
visibilities are then written with python-casacore: a point source of unit
amplitude seen through a per-antenna excess path L_p(t) (the troposphere is
non-dispersive: channel k sees 2*pi*nu_k*L/c, GUIDE section 3 "Wideband"), so
baseline p-q carries exp(i 2*pi*nu_k*(L_p - L_q)/c) on every channel of every
window, with the convention V_pq = g_p g_q^* of CASA's measurement equation.

Reference: one window of 16 x 125 MHz centred on 86.0 GHz; target: two windows
of 16 x 125 MHz centred on 227.1 and 229.1 GHz; 1-s integrations.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple

import numpy as np

C_LIGHT = 299_792_458.0
#: four of the paper's stations (ITRF metres, GUIDE section 2): all up together over M87 at the start time
STATIONS = {
    "PV": (5088967.74544, -301681.18586, 3825012.20561),
    "PB": (4524000.43, 468042.14, 4460309.76),
    "AP": (2225039.5297, -5441197.6292, -2479303.3597),
    "GL": (541547.0, -1387978.6, 6180982.0),
}
#: J2000 directions of the fields a pair may observe
FIELDS = {"M87": ("12h30m49.42s", "+12d23m28.04s"), "3C273": ("12h29m06.70s", "+02d03m08.6s")}
CHAN_WIDTH_HZ = 125e6
N_CHAN = 16
REF_CENTRES_HZ = (86.0e9,)
TARGET_CENTRES_HZ = (227.1e9, 229.1e9)


@dataclass(frozen=True)
class Pair:
    """The two sets and the truth written into them."""

    ref_ms: Path
    target_ms: Path
    times: np.ndarray          # (n_time,) MS TIME of the integrations
    path_m: np.ndarray         # (n_time, n_ant) excess path L_p(t), metres


def _first_channel(centre_hz: float) -> float:
    return centre_hz - (N_CHAN - 1) / 2 * CHAN_WIDTH_HZ


def lay_out(ms: Path, centres_hz: Sequence[float], scans: Sequence[Tuple[str, float, float]],
            start_utc: str, stations: Sequence[str], integration_s: float = 1.0) -> None:
    """An empty (zero DATA) set laid out by casatools.simulator: one window per centre, one
    scan per (field, start s, stop s) of ``scans``.

    The simulator runs in a process of its own: casatools.simulator's observe crashed
    (SIGSEGV) inside a pytest process that had already run other CASA tasks and
    eht-imaging, taking the whole session with it; a fresh process lays the set out
    the same way every time, and a failure is an ordinary error naming the step.
    """
    args = {"ms": str(ms), "centres_hz": list(centres_hz), "scans": [list(s) for s in scans],
            "start_utc": start_utc, "stations": list(stations), "integration_s": integration_s}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), json.dumps(args)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"casatools.simulator could not lay out {ms} (exit "
                           f"{proc.returncode}):\n{proc.stderr[-3000:]}")


def _lay_out_here(ms: Path, centres_hz: Sequence[float],
                  scans: Sequence[Tuple[str, float, float]], start_utc: str,
                  stations: Sequence[str], integration_s: float = 1.0) -> None:
    """:func:`lay_out`'s work, in this process."""
    from hitops.casa_env import ensure_casa_offline

    ensure_casa_offline()
    from casatools import measures, simulator

    me = measures()
    sm = simulator()
    shutil.rmtree(ms, ignore_errors=True)
    xyz = np.array([STATIONS[s] for s in stations])
    sm.open(str(ms))
    sm.setconfig(telescopename="EHT", x=xyz[:, 0].tolist(), y=xyz[:, 1].tolist(),
                 z=xyz[:, 2].tolist(), dishdiameter=[12.0] * len(stations),
                 mount=["alt-az"] * len(stations), antname=list(stations),
                 padname=list(stations), coordsystem="global",
                 referencelocation=me.position("ITRF", *(f"{v}m" for v in xyz[0])))
    for k, centre in enumerate(centres_hz):
        sm.setspwindow(spwname=f"spw{k}", freq=f"{_first_channel(centre)}Hz",
                       deltafreq=f"{CHAN_WIDTH_HZ}Hz", freqresolution=f"{CHAN_WIDTH_HZ}Hz",
                       nchannels=N_CHAN, stokes="RR LL")
    sm.setfeed(mode="perfect R L")
    for name in dict.fromkeys(field for field, _, _ in scans):
        sm.setfield(sourcename=name, sourcedirection=me.direction("J2000", *FIELDS[name]))
    sm.setlimits(shadowlimit=0.001, elevationlimit="0deg")
    sm.setauto(autocorrwt=0.0)
    sm.settimes(integrationtime=f"{integration_s}s", usehourangle=False,
                referencetime=me.epoch("UTC", start_utc))
    for field, start, stop in scans:
        for k in range(len(centres_hz)):
            sm.observe(sourcename=field, spwname=f"spw{k}", starttime=f"{start}s",
                       stoptime=f"{stop}s")
    sm.close()
    sm.done()


def excess_path(times: np.ndarray, n_ant: int, seed: int, scale_m: float) -> np.ndarray:
    """Smooth per-antenna excess paths (metres): a random walk of sinusoids, antenna 0 included."""
    rng = np.random.default_rng(seed)
    t = (times - times[0]) / max(times[-1] - times[0], 1.0)
    path = np.zeros((times.size, n_ant))
    for a in range(n_ant):
        for period in (2.0, 0.7, 0.3):
            amp = scale_m * rng.normal() * period
            path[:, a] += amp * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
        path[:, a] += 4 * scale_m * rng.normal() * t       # a drift: many wraps one way
    return path


def write_path_phases(ms: Path, times: np.ndarray, path_m: np.ndarray) -> None:
    """DATA = exp(i 2*pi*nu_k*(L_p - L_q)/c) on every row, channel and parallel hand; MODEL_DATA 1."""
    from casacore import tables as pt

    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        chan_freq = t.getcol("CHAN_FREQ")                 # (n_spw, n_chan)
    with pt.table(f"{ms}::DATA_DESCRIPTION", ack=False) as t:
        spw_of_ddid = t.getcol("SPECTRAL_WINDOW_ID")
    with pt.table(str(ms), readonly=False, ack=False) as t:
        it = np.searchsorted(times, t.getcol("TIME"))
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        freq = chan_freq[spw_of_ddid[t.getcol("DATA_DESC_ID")]]   # (n_row, n_chan)
        delta = (path_m[it, a1] - path_m[it, a2])[:, None]
        phase = 2 * np.pi * freq * delta / C_LIGHT
        n_corr = t.getcell("DATA", 0).shape[1]
        data = np.repeat(np.exp(1j * phase)[:, :, None], n_corr, axis=2).astype(np.complex64)
        t.putcol("DATA", data)
        t.putcol("FLAG", np.zeros(data.shape, bool))
        # the simulator leaves MODEL_DATA zero; gaincal divides by the model (a 1 Jy point)
        t.putcol("MODEL_DATA", np.ones(data.shape, np.complex64))


def make_solution_pair(workdir: Path, stations: Sequence[str] = ("PV", "PB", "AP", "GL"),
                       duration_s: float = 1200.0, seed: int = 1, scale_m: float = 0.01,
                       start_utc: str = "2023/04/10/03:00:00",
                       ref_centres_hz: Sequence[float] = REF_CENTRES_HZ,
                       scans: Optional[Sequence[Tuple[str, float, float]]] = None) -> Pair:
    """The pair: ``scans`` (field, start s, stop s) default to one scan of M87 of ``duration_s``."""
    from casacore import tables as pt

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = workdir / "ref.ms", workdir / "target.ms"
    scans = scans or (("M87", 0.0, duration_s),)
    lay_out(ref_ms, ref_centres_hz, scans, start_utc, stations)
    lay_out(target_ms, TARGET_CENTRES_HZ, scans, start_utc, stations)
    with pt.table(str(ref_ms), ack=False) as t:
        times = np.unique(t.getcol("TIME"))
    path = excess_path(times, len(stations), seed, scale_m)
    write_path_phases(ref_ms, times, path)
    write_path_phases(target_ms, times, path)
    return Pair(ref_ms, target_ms, times, path)


def fringe_fitted_pair(workdir: Path) -> Tuple[Pair, Path]:
    """The default pair and CASA fringefit's 4-s solutions of its reference band:
    (pair, table); fringefit needs at least two integrations per solution."""
    from hitops.casa.tasks import fringefit

    pair = make_solution_pair(workdir)
    table = Path(workdir) / "ref.fringe"
    fringefit(str(pair.ref_ms), str(table), solint="4s", refant="PV,PB", minsnr=3.0)
    return pair, table


def refant_sets_halfway(pair: Pair, workdir: Path) -> Tuple[Path, Path]:
    """A copy of the pair's REF_MS with PV (antenna 0) flagged for the second half, and
    CASA fringefit's 4-s table of it, which refers to PB from then on: (ref_ms, table)."""
    from casacore import tables as pt

    from hitops.casa.tasks import fringefit

    ref_ms = Path(workdir) / "ref_pv_sets.ms"
    shutil.copytree(pair.ref_ms, ref_ms)
    half = pair.times[pair.times.size // 2]
    with pt.table(str(ref_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        pv = ((t.getcol("ANTENNA1") == 0) | (t.getcol("ANTENNA2") == 0)) & (t.getcol("TIME") >= half)
        flag[pv] = True
        t.putcol("FLAG", flag)
    table = Path(workdir) / "ref.fringe"
    fringefit(str(ref_ms), str(table), solint="4s", refant="PV,PB", minsnr=3.0)
    return ref_ms, table


if __name__ == "__main__":   # lay_out's own process
    _lay_out_here(**json.loads(sys.argv[1]))
