"""Observation geometry: time grid, (u, v, w) and elevations from casacore measures.

The (u, v, w) of a station at time t is M(t) @ X, where X is its ITRF
position and M(t) the 3x3 matrix casacore's measures apply to an ITRF
baseline (``measures().to_uvw`` in the J2000 frame of the phase centre:
polar motion and UT1 from the IERS tables in casacore's data, Earth
rotation, nutation, precession, aberration).  casacore's conversion is a
rotation, linear in the baseline (uvw(X1) - uvw(X2) = uvw(X1 - X2) to
1e-8 m), so one matrix per time serves every station and baseline.

Calling casacore once per time is slow (~0.6 ms per epoch with the cache
refill below, ~26 s for a 12 h track at 1 s), so M(t) is taken from
casacore every minute and fitted: M(t) = A(t) Rz(theta(t)) where theta is
the Earth rotation angle (IERS Conventions 2010, eq. 5.15, UTC for UT1) and
A(t) holds only the slow terms (precession, nutation, UT1-UTC, polar
motion, aberration), fitted by a Chebyshev series.

Three properties of casacore 3.x set how the samples are taken (measured
in docs/simulate.md, "Geometry"; tests/test_simulate_geometry.py):

* ``MeasTable::dUT1`` and ``MeasTable::polarMotion`` keep the last IERS
  value in a static cache and return it unchanged for any epoch within
  0.04 d (58 min) of the epoch that filled it: no interpolation, and no
  aipsrc switch (the ``measures.*.d_interval`` variables govern other
  caches and change nothing here).  One call's answer thus depends on the
  calls before it, by up to ~5 mm on 10^4 km baselines in April 2023, when
  UT1-UTC drifted by 0.15-0.36 ms per day.  Every sample is therefore
  preceded by a call one day later, which makes both caches refill at the
  sample's own epoch: the result equals a fresh process's (to < 1e-6 m)
  whatever the call order.
* casacore interpolates UT1-UTC and polar motion linearly between the
  daily IERS entries, so A(t) has a kink at every 0h UTC: fits never span
  one.
* casacore's Earth rotation moves in steps of 1.254 us of time (two float64
  ulps of an MJD-day epoch; measured by stepping the epoch through
  consecutive float64 values), so a single evaluation sits up to ~1 us
  along the track from the smooth curve (0.4 us rms: 0.2 mm rms, up to
  ~0.8 mm on 10^4 km).  The fit averages this out (its own error is
  ~0.05 mm rms on 12 500 km), and theta(t) here is computed from whole days
  and seconds of day separately, keeping full float64 time precision.

Frame position: casacore applies its diurnal aberration of the frame's
observer (``MeasMath::deapplyTOPOtoHADEC`` with ``MeasTable::diurnalAber``)
as a rotation of the whole baseline, so to_uvw moves by ~1.5e-6 of the
baseline length (11-22 m on 9 300 km) when the frame position moves from
one station to another (or to the geocentre).  hitops uses one array
reference position for all rows, the scene's first station.

Sign convention: UVW of a row = uvw(ANTENNA1) - uvw(ANTENNA2), i.e.
``to_uvw`` of the baseline X1 - X2, as casatools.simulator writes it
(checked row by row in tests/test_simulate_tools.py); a sky offset (l east,
m north) then enters as V = exp(+2 pi i (u l + v m)) in the stored UVW,
which WSClean images east-left, north-up (checked in the same tests).
casacore's TaQL ``MSCAL.UVWJ2000()`` returns the opposite sign.
"""

from __future__ import annotations

import numpy as np

# Earth rotation and the local zenith are shared with calibrate (elevations)
from ..geometry import DAY, earth_rotation_angle, geodetic_up

#: casacore refills its dUT1 / polar-motion caches only for epochs more than
#: 0.04 d from the cached one; a call this far away forces the refill
_CACHE_FLUSH_OFFSET = DAY


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

    ``position`` is casacore's frame position (see the module docstring:
    the result depends on it through casacore's diurnal aberration).  Each
    epoch is preceded by a call one day later so that casacore's static
    UT1-UTC and polar-motion caches are refilled at that epoch: the result
    does not depend on earlier calls in the process.
    """
    from casacore import quanta as qa
    from casacore.measures import measures

    dm = measures()
    dm.do_frame(dm.position("ITRF", *[qa.quantity(float(x), "m") for x in position]))
    dm.do_frame(dm.direction("J2000", qa.quantity(ra, "rad"), qa.quantity(dec, "rad")))
    unit = dm.baseline("ITRF", qa.quantity([1.0, 0.0, 0.0], "m"),
                       qa.quantity([0.0, 1.0, 0.0], "m"), qa.quantity([0.0, 0.0, 1.0], "m"))
    out = np.empty((len(times), 3, 3))
    for i, t in enumerate(np.asarray(times, dtype=np.float64)):
        dm.do_frame(dm.epoch("UTC", qa.quantity(float(t) + _CACHE_FLUSH_OFFSET, "s")))
        dm.to_uvw(unit)
        dm.do_frame(dm.epoch("UTC", qa.quantity(float(t), "s")))
        xyz = np.asarray(dm.to_uvw(unit)["xyz"].get_value("m"), dtype=np.float64)
        # xyz holds the uvw of unit vectors x, y, z in turn: columns of M
        out[i] = xyz.reshape(3, 3).T
    return out


def fit_segments(t_lo: float, t_hi: float, segment: float) -> list:
    """[(lo, hi)] covering [t_lo, t_hi], split at UTC midnights and at most ``segment`` long.

    casacore interpolates the daily IERS UT1-UTC and polar motion linearly,
    so the slow part A(t) has a kink at 0h UTC that no smooth fit should span.
    """
    midnights = np.arange(np.floor(t_lo / DAY) + 1.0, np.ceil(t_hi / DAY)) * DAY
    edges = np.concatenate([[t_lo], midnights[(midnights > t_lo) & (midnights < t_hi)], [t_hi]])
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        n_piece = max(int(np.ceil((hi - lo) / segment)), 1)
        cuts = np.linspace(lo, hi, n_piece + 1)
        out.extend(zip(cuts[:-1], cuts[1:]))
    return out


def uvw_matrices(times: np.ndarray, ra: float, dec: float, position: np.ndarray,
                 sample_step: float = 60.0, segment: float = 43200.0,
                 degree: int = 10) -> np.ndarray:
    """M(t) for every time (n, 3, 3).

    On each segment of :func:`fit_segments`, casacore is sampled every
    ``sample_step`` seconds (all samples inside the segment, at least
    10 per fitted coefficient) and its slow part A(t) = M(t) Rz(theta(t))^T
    is fitted by least squares with a Chebyshev series of ``degree``
    (fewer on segments shorter than 7 h: the term least like a polynomial,
    casacore's diurnal aberration with its one-day period, is then closer
    to linear).
    A fit rather than an interpolation: single casacore evaluations jitter
    by ~0.4 us in time (module docstring), which the fit averages out.
    """
    times = np.asarray(times, dtype=np.float64)
    out = np.zeros((times.size, 3, 3))
    if times.size == 0:
        return out
    segments = fit_segments(times.min(), times.max(), segment)
    for k, (lo, hi) in enumerate(segments):
        last = k == len(segments) - 1
        sel = (times >= lo) & ((times <= hi) if last else (times < hi))
        if not sel.any():
            continue
        if hi - lo < 1.0:
            # a single epoch (a one-integration track): nothing to fit
            out[sel] = casacore_uvw_matrix(times[sel], ra, dec, position)
            continue
        n_coef = min(degree, 3 + int(np.ceil((hi - lo) / 3600.0))) + 1
        n_samples = max(int(np.ceil((hi - lo) / sample_step)) + 1, 10 * n_coef)
        samples = np.linspace(lo, hi, n_samples)
        m_samples = casacore_uvw_matrix(samples, ra, dec, position)
        # strip the Earth rotation: A = M Rz(theta)^-1 varies slowly
        slow = m_samples @ np.swapaxes(_rz(earth_rotation_angle(samples)), -1, -2)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        coef = np.polynomial.chebyshev.chebfit((samples - centre) / half,
                                               slow.reshape(n_samples, 9), n_coef - 1)
        a_t = np.polynomial.chebyshev.chebval((times[sel] - centre) / half, coef).T
        out[sel] = a_t.reshape(-1, 3, 3) @ _rz(earth_rotation_angle(times[sel]))
    return out


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


def alternating_grid(start_mjd_s: float, duration: float, integration: float,
                     target_scan: float, calibrator_scan: float, scan_gap: float = 0.0):
    """Integration centres of a target observed in scans alternating with a calibrator's.

    One cycle is a target scan of ``target_scan`` s, a gap, a calibrator scan of
    ``calibrator_scan`` s and another gap (``scan_gap`` s each, the slews); an
    integration belongs to a scan when it lies entirely within it.  Scans are numbered
    from 1 in time order (target 1, calibrator 2, target 3, ...).  Returns (centres (n,),
    scan numbers (n,), on source (n,) bool, field index (n,) int32: 0 target,
    1 calibrator).
    """
    n_int = int(np.floor(duration / integration + 1e-9))
    offsets = np.arange(n_int) * integration
    centres = start_mjd_s + offsets + 0.5 * integration
    cycle = target_scan + calibrator_scan + 2.0 * scan_gap
    within = np.mod(offsets + 1e-9, cycle)
    n_cycle = np.floor((offsets + 1e-9) / cycle).astype(np.int32)
    cal_start = target_scan + scan_gap
    on_target = within + integration <= target_scan + 1e-6
    on_calibrator = (within >= cal_start - 1e-6) & (within + integration
                                                    <= cal_start + calibrator_scan + 1e-6)
    field_id = on_calibrator.astype(np.int32)
    scan = 2 * n_cycle + 1 + field_id
    return centres, scan.astype(np.int32), on_target | on_calibrator, field_id
