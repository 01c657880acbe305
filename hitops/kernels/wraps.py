"""Counting the 2*pi wraps of a wrapped reference-phase series.

Paper (fpt-arbitrary-ratios.tex, "Phase-wrap counting"): a wrapped phase in
[-pi, pi) that crosses the boundary from the -pi side jumps by +2*pi, so the
wrap count n(t) goes up by one; crossing from the +pi side it goes down by
one.  A step of magnitude > pi between consecutive samples is taken as a wrap
(valid while the Itoh condition holds: true steps stay below pi).

``count_wraps`` is the reference tracker; alternative trackers (issue 6,
``hitops/kernels/tracking.py``) share its signature
``(ref_phase: float64[n_time], valid: bool[n_time]) -> int64[n_time]`` and are
registered by name in :data:`TRACKERS`.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def count_wraps(ref_phase, valid):
    """Cumulative wrap count n(t) of ``ref_phase`` (radians, wrapped).

    Starts at 0; a step > pi between consecutive *valid* samples is a wrap
    (+1 when the phase jumps up, i.e. crossed from the -pi side, -1 when it
    jumps down).  Invalid or non-finite samples take no part and carry the
    previous count.
    """
    n_time = ref_phase.shape[0]
    wraps = np.zeros(n_time, dtype=np.int64)
    count = 0
    have_last = False
    last = 0.0
    for t in range(n_time):
        phase = ref_phase[t]
        if valid[t] and math.isfinite(phase):
            if have_last:
                step = phase - last
                if step > math.pi:
                    count += 1
                elif step < -math.pi:
                    count -= 1
            last = phase
            have_last = True
        wraps[t] = count
    return wraps


@numba.njit(cache=True, nogil=True)
def wrap_events(wraps, scan_of_time):
    """Number of wraps counted in each series of ``wraps`` (..., n_time): sum of |steps|.

    Steps between two scans are not wraps: the count restarts at 0 in every
    scan, and that reset must not be reported as wrap events.
    """
    flat = wraps.reshape(-1, wraps.shape[-1])
    events = np.zeros(flat.shape[0], dtype=np.int64)
    for s in range(flat.shape[0]):
        for t in range(1, flat.shape[1]):
            if scan_of_time[t] == scan_of_time[t - 1]:
                events[s] += abs(flat[s, t] - flat[s, t - 1])
    return events.reshape(wraps.shape[:-1])


#: trackers by name; each maps (ref_phase[n_time], valid[n_time]) -> int64[n_time]
TRACKERS = {"count": count_wraps}


def get_tracker(name: str):
    """The tracker registered as ``name`` (issue 6 adds more in kernels/tracking.py)."""
    from ..errors import InputError

    try:
        from . import tracking  # noqa: F401  (importing it registers its trackers)
    except ImportError:
        pass
    if name not in TRACKERS:
        raise InputError(f"unknown wrap tracker '{name}'; known: {', '.join(sorted(TRACKERS))}")
    return TRACKERS[name]
