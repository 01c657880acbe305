"""Observation geometry: time grid, (u, v, w) and elevations from casacore measures.

The (u, v, w) of a station at time t is M(t) @ X, where X is its ITRF
position and M(t) the 3x3 matrix casacore's measures apply to an ITRF
baseline (``measures().to_uvw`` in the J2000 frame of the phase centre:
precession, nutation, Earth rotation with IERS UT1 and polar motion from
casadata).  Calling casacore once per time is slow (~0.3 ms per call, ~13 s for a
12 h track at 1 s), so M(t) is taken from casacore every minute and fitted:
M(t) = A(t) Rz(theta(t)) where theta is the Earth rotation angle (IERS
Conventions 2010, eq. 5.15) and A(t) holds only the slow terms (precession,
nutation, UT1-UTC, polar motion), which a low-order Chebyshev series fits
to well below a millimetre on Earth-sized baselines (checked against
casacore row by row in tests/test_simulate_geometry.py).

Sign convention: UVW of a row = uvw(ANTENNA1) - uvw(ANTENNA2), i.e.
``to_uvw`` of the baseline X1 - X2, as casatools.simulator writes it
(checked row by row in tests/test_simulate_tools.py); a sky offset (l east,
m north) then enters as V = exp(+2 pi i (u l + v m)) in the stored UVW,
which WSClean images east-left, north-up (checked in the same tests).
casacore's TaQL ``MSCAL.UVWJ2000()`` returns the opposite sign.
"""

from __future__ import annotations

import numpy as np

#: seconds per day
DAY = 86400.0
#: Earth rotation angle rate, turns per UT1 day (IERS Conventions 2010, eq. 5.15)
ERA_RATE = 1.00273781191135448
ERA_J2000 = 0.7790572732640
MJD_J2000 = 51544.5

#: WGS84 ellipsoid (NIMA TR8350.2)
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563


def earth_rotation_angle(time_mjd_s: np.ndarray) -> np.ndarray:
    """Earth rotation angle (rad) with UTC standing in for UT1 (the difference goes into A(t))."""
    days = np.asarray(time_mjd_s) / DAY - MJD_J2000
    # split the product to keep precision: fractional turns only
    turns = ERA_J2000 + np.mod(days, 1.0) + (ERA_RATE - 1.0) * days + np.floor(days)
    return 2.0 * np.pi * np.mod(turns, 1.0)


def _rz(theta: np.ndarray) -> np.ndarray:
    """Rotation matrices about z by theta, shape (n, 3, 3)."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.zeros(np.shape(theta) + (3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def casacore_uvw_matrix(times: np.ndarray, ra: float, dec: float,
                        position: np.ndarray) -> np.ndarray:
    """M(t) (n, 3, 3) from casacore: uvw = M @ itrf_baseline, J2000 frame of (ra, dec).

    ``position`` is casacore's frame position: to_uvw applies the observer's
    aberration, which moves UVW by ~20 m on 10^4 km baselines between
    stations, so the simulator uses one array reference (the first station).
    """
    from casacore import quanta as qa
    from casacore.measures import measures

    dm = measures()
    dm.do_frame(dm.position("ITRF", *[qa.quantity(float(x), "m") for x in position]))
    dm.do_frame(dm.direction("J2000", qa.quantity(ra, "rad"), qa.quantity(dec, "rad")))
    unit = dm.baseline("ITRF", qa.quantity([1.0, 0.0, 0.0], "m"),
                       qa.quantity([0.0, 1.0, 0.0], "m"), qa.quantity([0.0, 0.0, 1.0], "m"))
    out = np.empty((len(times), 3, 3))
    for i, t in enumerate(times):
        dm.do_frame(dm.epoch("UTC", qa.quantity(float(t), "s")))
        xyz = np.asarray(dm.to_uvw(unit)["xyz"].get_value("m"), dtype=np.float64)
        # xyz holds the uvw of unit vectors x, y, z in turn: columns of M
        out[i] = xyz.reshape(3, 3).T
    return out


def uvw_matrices(times: np.ndarray, ra: float, dec: float, position: np.ndarray,
                 sample_step: float = 60.0, segment: float = 43200.0, degree: int = 6) -> np.ndarray:
    """M(t) for every time (n, 3, 3).

    casacore is sampled every ``sample_step`` seconds; its slow part A(t)
    is fitted by least squares with a Chebyshev series of ``degree`` on
    segments of at most ``segment`` seconds.  A fit rather than an
    interpolation: single casacore evaluations scatter by ~0.5 mm (a few mm
    at worst) on 10^4 km baselines around their smooth trend, and the fit
    averages that scatter out.
    """
    times = np.asarray(times, dtype=np.float64)
    out = np.zeros((times.size, 3, 3))
    if times.size == 0:
        return out
    t_lo, t_hi = times.min(), times.max()
    n_seg = max(int(np.ceil((t_hi - t_lo) / segment)), 1)
    edges = np.linspace(t_lo, t_hi, n_seg + 1)
    for k in range(n_seg):
        lo, hi = edges[k], edges[k + 1]
        n_samples = max(int(np.ceil((hi - lo) / sample_step)) + 1, 3 * (degree + 1))
        samples = np.linspace(lo - sample_step, hi + sample_step, n_samples)
        m_samples = casacore_uvw_matrix(samples, ra, dec, position)
        # strip the Earth rotation: A = M Rz(theta)^-1 varies slowly
        slow = m_samples @ np.swapaxes(_rz(earth_rotation_angle(samples)), -1, -2)
        centre, half = 0.5 * (samples[0] + samples[-1]), 0.5 * (samples[-1] - samples[0])
        coef = np.polynomial.chebyshev.chebfit((samples - centre) / half,
                                               slow.reshape(n_samples, 9), degree)
        sel = (times >= lo) & (times <= hi) if k < n_seg - 1 else (times >= lo)
        a_t = np.polynomial.chebyshev.chebval((times[sel] - centre) / half, coef).T
        out[sel] = a_t.reshape(-1, 3, 3) @ _rz(earth_rotation_angle(times[sel]))
    return out


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


def station_uvw(matrices: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """uvw (n_station, n_time, 3) of each station position under M(t)."""
    return np.einsum("tij,sj->sti", matrices, np.asarray(positions, dtype=np.float64))


def station_elevation(matrices: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Elevation (rad) of the phase centre at each station, (n_station, n_time).

    The w axis of M(t) (its third row) is the source direction expressed in
    ITRF; its dot product with the local geodetic zenith is sin(elevation).
    Refraction and diurnal aberration (< 1 arcmin) are ignored.
    """
    source_itrf = matrices[:, 2, :]
    source_itrf = source_itrf / np.linalg.norm(source_itrf, axis=-1, keepdims=True)
    up = geodetic_up(positions)
    return np.arcsin(np.clip(up @ source_itrf.T, -1.0, 1.0))


def time_grid(start_mjd_s: float, duration: float, integration: float,
              scan_length: float | None = None, scan_gap: float = 0.0):
    """Integration centres and scan numbers.

    Integrations of length ``integration`` tile [start, start + duration);
    with a scan pattern, an integration belongs to a scan when it lies
    entirely within the first ``scan_length`` seconds of a
    ``scan_length + scan_gap`` cycle.  Returns (centres (n,), scan numbers
    (n,) from 1, whether each integration is on source (n,) bool).
    """
    n_int = int(np.floor(duration / integration + 1e-9))
    offsets = np.arange(n_int) * integration
    centres = start_mjd_s + offsets + 0.5 * integration
    if scan_length:
        cycle = scan_length + scan_gap
        phase = np.mod(offsets + 1e-9, cycle)
        on_source = phase + integration <= scan_length + 1e-6
        scan = (np.floor((offsets + 1e-9) / cycle)).astype(np.int32) + 1
    else:
        on_source = np.ones(n_int, bool)
        scan = np.ones(n_int, np.int32)
    return centres, scan, on_source
