"""Lay out a scene with casatools.simulator (no corruption, no noise): the CASA baseline.

Run as ``python benchmarks/casa_layout.py SCENE OUT.ms [--band NAME] [--duration S]
[--integration S] [--stations A,B] [--elevation-limit DEG] [--correlations RR,RL,LR,LL]`` in its own process so the benchmark can time it and read
its peak memory.  Used by benchmarks/bench_simulate.py (speed comparison) and
tests/test_simulate_casa.py (UVW sign convention and time scale cross-check).
"""

from __future__ import annotations

import argparse
import shutil
import sys

import numpy as np


def casa_layout(scene_name: str, ms_path: str, band_name: str | None = None,
                duration: float | None = None, stations: str | None = None,
                elevation_limit_deg: float | None = None,
                integration: float | None = None, correlations: str | None = None) -> None:
    from hitops.casa_env import ensure_casa_offline
    from hitops.simulate.scene import apply_overrides, parse_scene

    ensure_casa_offline()
    from casatools import measures, simulator

    scene = apply_overrides(parse_scene(scene_name), duration=duration, stations=stations,
                            integration=integration, correlations=correlations)
    band = next(b for b in scene.bands if band_name in (None, b.name))
    positions = np.array([s.itrf for s in scene.stations])
    me = measures()
    sm = simulator()
    shutil.rmtree(ms_path, ignore_errors=True)
    sm.open(ms_path)
    sm.setconfig(telescopename=scene.telescope, x=positions[:, 0].tolist(),
                 y=positions[:, 1].tolist(), z=positions[:, 2].tolist(),
                 dishdiameter=[s.diameter for s in scene.stations],
                 mount=["alt-az"] * len(scene.stations),
                 antname=[s.code for s in scene.stations],
                 padname=[s.name for s in scene.stations],
                 coordsystem="global",
                 referencelocation=me.position("ITRF", f"{positions[0, 0]}m",
                                               f"{positions[0, 1]}m", f"{positions[0, 2]}m"))
    sm.setspwindow(spwname=f"band{band.name}", freq=f"{band.freq_hz}Hz",
                   deltafreq=f"{band.bandwidth_hz}Hz", freqresolution=f"{band.bandwidth_hz}Hz",
                   nchannels=1, stokes=" ".join(scene.correlations))
    sm.setfeed(mode="perfect R L")
    sm.setfield(sourcename=scene.source_name,
                sourcedirection=me.direction("J2000", f"{scene.ra}rad", f"{scene.dec}rad"))
    limit = scene.stations[0].elevation_limit if elevation_limit_deg is None else elevation_limit_deg
    sm.setlimits(shadowlimit=0.001, elevationlimit=f"{limit}deg")
    sm.setauto(autocorrwt=0.0)
    sm.settimes(integrationtime=f"{scene.integration}s", usehourangle=False,
                referencetime=me.epoch("UTC", f"{scene.start_mjd_s}s"))
    sm.observe(sourcename=scene.source_name, spwname=f"band{band.name}", starttime="0s",
               stoptime=f"{scene.duration}s")
    sm.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("scene")
    parser.add_argument("ms")
    parser.add_argument("--band")
    parser.add_argument("--duration", type=float)
    parser.add_argument("--stations")
    parser.add_argument("--elevation-limit", type=float)
    parser.add_argument("--integration", type=float)
    parser.add_argument("--correlations", help="e.g. RR,RL,LR,LL (default: the scene's)")
    args = parser.parse_args(argv)
    casa_layout(args.scene, args.ms, args.band, args.duration, args.stations, args.elevation_limit,
                args.integration, args.correlations)
    return 0


if __name__ == "__main__":
    sys.exit(main())
