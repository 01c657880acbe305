"""Earth geometry that both the simulator and calibrate use: Earth rotation, local zenith,
elevation of the phase centre at each station.

``hitops simulate`` builds its (u, v, w) and elevations from casacore measures
(:mod:`hitops.simulate.geometry`), stripping the Earth rotation with
:func:`earth_rotation_angle`; ``hitops calibrate`` only needs sin(elevation) per
station to scale the coherence time as sin(el)^(3/5) (docs/tracking.md), so it
uses the same angle and the same WGS84 zenith without casacore.  The functions
live here so that calibrate does not import the simulator.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: seconds per day
DAY = 86400.0
#: Earth rotation angle rate, turns per UT1 day (IERS Conventions 2010, eq. 5.15)
ERA_RATE = 1.00273781191135448
#: ERA_RATE - 1 written out: ERA_RATE - 1.0 in float64 is off by ~5e-12 rad after 23 years
ERA_RATE_EXCESS = 0.00273781191135448
ERA_J2000 = 0.7790572732640
MJD_J2000 = 51544.5

#: WGS84 ellipsoid (NIMA TR8350.2)
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563

#: distance from the Earth's centre (m) of a station on its surface, with margin:
#: positions outside it are synthetic (zeros, test layouts), not a geometry
SURFACE_RADIUS_M = (6.33e6, 6.40e6)


def earth_rotation_angle(time_mjd_s: np.ndarray) -> np.ndarray:
    """Earth rotation angle (rad) with UTC standing in for UT1 (the difference goes into A(t)).

    The time is split into whole days and seconds of day before dividing:
    t / 86400 as one float64 would round to 0.63 us (0.3 mm on 10^4 km).
    """
    since_j2000 = np.asarray(time_mjd_s, dtype=np.float64) - MJD_J2000 * DAY   # exact
    whole_days = np.floor(since_j2000 / DAY)
    day_fraction = (since_j2000 - whole_days * DAY) / DAY                      # exact numerator
    turns = (ERA_J2000 + np.mod(ERA_RATE_EXCESS * whole_days, 1.0)
             + ERA_RATE_EXCESS * day_fraction + day_fraction)
    return 2.0 * np.pi * np.mod(turns, 1.0)


def geodetic_up(position: np.ndarray) -> np.ndarray:
    """Unit normal to the WGS84 ellipsoid (local zenith) at ITRF positions (n, 3)."""
    x, y, z = np.asarray(position, dtype=np.float64).T
    e2 = WGS84_F * (2.0 - WGS84_F)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - e2))
    for _ in range(6):   # Bowring-style fixed point, converges to < 1e-12 rad
        n_rad = WGS84_A / np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n_rad
        lat = np.arctan2(z, p * (1.0 - e2 * n_rad / (n_rad + h)))
    lon = np.arctan2(y, x)
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def sin_elevation(positions: np.ndarray, ra: float, dec: float,
                  times: np.ndarray) -> Optional[np.ndarray]:
    """sin(elevation) of the J2000 direction (ra, dec) at each ITRF station, (n_ant, n_time);
    None when the positions are not on the Earth's surface (no usable geometry).

    The direction is rotated into ITRF by the Earth rotation angle only
    (precession and nutation, ~0.3 deg since 2000, are ignored): good enough
    for the sin(el)^(3/5) scaling of the coherence time.
    """
    positions = np.asarray(positions, dtype=np.float64)
    radius = np.linalg.norm(positions, axis=1) if positions.size else np.zeros(0)
    lo, hi = SURFACE_RADIUS_M
    if radius.size == 0 or np.any((radius < lo) | (radius > hi)):
        return None
    hour = earth_rotation_angle(times) - ra     # Greenwich hour angle
    src = np.stack([np.cos(dec) * np.cos(hour), -np.cos(dec) * np.sin(hour),
                    np.full(np.shape(times), np.sin(dec))], axis=0)
    return geodetic_up(positions) @ src


def station_sin_elevation(ms: str, times: np.ndarray, meta=None) -> Optional[np.ndarray]:
    """:func:`sin_elevation` of the first phase centre of ``ms`` at its ANTENNA positions;
    None when the set has no usable geometry (positions off the Earth's surface, no field).
    ``meta``: the run's ``hitops.io.metadata.SetMetadata`` of ``ms``, read here when None."""
    if meta is None:
        from .io.metadata import read_metadata   # casacore only when a set is read
        meta = read_metadata(ms)
    positions = meta.antennas.positions
    positions = np.zeros((0, 3)) if positions is None else positions
    if meta.fields.phase_dirs.size == 0:
        return None
    ra, dec = meta.fields.phase_dirs[0]
    return sin_elevation(positions, ra, dec, np.asarray(times, dtype=np.float64))
