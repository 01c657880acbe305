"""Wrap counting on antenna solution series, the rates bridging consecutive solutions.

A solution phase is known modulo 2*pi.  Between consecutive solutions of one antenna
the kernel predicts the next phase from the last unwrapped one and the rates,

    predicted = u_prev + 2*pi*nu_ref * (rate_prev + rate_next)/2 * dt

(the trapezoid of the two solutions' rates; without rates, predicted = u_prev, the
paper's step counter), and takes the branch of the new phase nearest the prediction:
u = phase + offset + 2*pi*n with n = round((predicted - phase - offset) / 2*pi).  The
bridged residual u - predicted is kept: while the Itoh condition holds for the
*residual* it stays well inside (-pi, pi); uniform residuals say the phase moved by
more than pi between solutions in a way the rates do not explain.

Reference antenna changes (fringefit takes the next antenna of its list when the first
sets): every antenna's phase in frame y is its phase in frame x minus y's phase in x,
a term common to all antennas at one time.  It cancels on every baseline, but only if
every antenna's count treats it alike, so the series are re-referred to the first
frame: at a switch x -> y the frame offset becomes the mean, over the antennas solved
both before and at the switch ("bridges"), of predicted u_b - phase_b(y).  Antenna y
itself (phase 0 in its own frame) is one of them when it was solved before.  Without
a bridge the offset is kept and the switch is reported as unbridged.

After a gap (a new scan, or more than ``max_gap`` seconds without a solution) the
rates are not trusted: the branch nearest the last unwrapped phase is taken, which
leaves each antenna an unknown integer per segment (antenna-based, so closure phases
keep; a later per-scan phase calibration absorbs it).

Tables without rates (G, T Jones) are bridged with the slope of each antenna's last two
unwrapped solutions instead (a linear extrapolation; the paper's step counter is the
zero-slope case, ``PREDICT_NONE``).

The kernel is pure: it never mutates its inputs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

TWO_PI = 2.0 * math.pi
#: switch codes of :func:`unwrap_solutions`
NO_SWITCH, BRIDGED, UNBRIDGED = 0, 1, 2
#: predictions of :func:`unwrap_solutions`: none (the paper's step counter), the table's
#: rates (Fringe Jones), or the slope of the last two solutions (tables without rates)
PREDICT_NONE, PREDICT_RATES, PREDICT_SLOPE = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def _wrap(x):
    return (x + math.pi) % TWO_PI - math.pi


@numba.njit(cache=True, nogil=True)
def _frame_offset(phase, valid, s, have, last_u, last_rate, last_t, times, new_segment, offset):
    """Offset of the frame at solution ``s`` from the bridges' predictions; (offset, bridged)."""
    n_ant = phase.shape[1]
    first = 0.0
    total = 0.0
    n = 0
    for b in range(n_ant):
        if not (valid[s, b] and have[b]):
            continue
        drift = 0.0 if new_segment[s] else last_rate[b] * (times[s] - last_t[b])
        estimate = last_u[b] + drift - phase[s, b]
        if n == 0:
            first = estimate
        # a circular mean anchored on the first estimate: every bridge names the same offset
        total += first + _wrap(estimate - first)
        n += 1
    if n == 0:
        return offset, False
    return total / n, True


@numba.njit(cache=True, nogil=True)
def unwrap_solutions(phase, valid, times, phase_rate, refant, new_segment, predict):
    """Unwrapped common-frame phases of every antenna of one receptor.

    phase: (n_sol, n_ant) float64 wrapped solution phases (rad); valid: (n_sol, n_ant) bool;
    times: (n_sol,) float64 s; phase_rate: (n_sol, n_ant) float64 rad/s (2*pi*nu_ref*rate;
    zeros when the table has none); refant: (n_sol,) int reference antenna (-1: unknown,
    taken as unchanged); new_segment: (n_sol,) bool, True where a scan or a gap starts;
    predict: PREDICT_NONE, PREDICT_RATES (trapezoid of the table's rates) or
    PREDICT_SLOPE (the slope of the antenna's last two unwrapped solutions in the segment).

    Returns unwrapped (n_sol, n_ant) float64 (NaN where invalid), wraps (n_sol, n_ant)
    int64 (unwrapped = phase + offset + 2*pi*wraps), offset (n_sol,) float64 (the frame
    offset added at each time), residual (n_sol, n_ant) float64 (unwrapped - predicted;
    NaN at an antenna's first solution and where invalid) and switch (n_sol,) int8
    (NO_SWITCH, BRIDGED, UNBRIDGED: a reference antenna change at that time).
    """
    n_sol, n_ant = phase.shape
    unwrapped = np.full((n_sol, n_ant), np.nan)
    wraps = np.zeros((n_sol, n_ant), dtype=np.int64)
    offsets = np.zeros(n_sol)
    residual = np.full((n_sol, n_ant), np.nan)
    switch = np.zeros(n_sol, dtype=np.int8)
    have = np.zeros(n_ant, dtype=np.bool_)
    last_u = np.zeros(n_ant)
    last_rate = np.zeros(n_ant)
    last_t = np.zeros(n_ant)
    last_n = np.zeros(n_ant, dtype=np.int64)
    offset = 0.0
    frame = -1
    for s in range(n_sol):
        changed = refant[s] >= 0 and frame >= 0 and refant[s] != frame
        if changed:
            offset, bridged = _frame_offset(phase, valid, s, have, last_u, last_rate, last_t,
                                            times, new_segment, offset)
            switch[s] = BRIDGED if bridged else UNBRIDGED
        if refant[s] >= 0:
            frame = refant[s]
        offsets[s] = offset
        for a in range(n_ant):
            if not valid[s, a]:
                continue
            x = phase[s, a] + offset
            n = last_n[a]
            if have[a]:
                dt = times[s] - last_t[a]
                if new_segment[s] or predict == PREDICT_NONE:
                    predicted = last_u[a]
                elif changed or predict == PREDICT_SLOPE:
                    # after a switch the table's rates are in the new frame: extrapolate the old
                    predicted = last_u[a] + last_rate[a] * dt
                else:
                    predicted = last_u[a] + 0.5 * (last_rate[a] + phase_rate[s, a]) * dt
                n = np.int64(round((predicted - x) / TWO_PI))
                residual[s, a] = x + TWO_PI * n - predicted
            u = x + TWO_PI * n
            if predict == PREDICT_SLOPE:
                same = have[a] and not new_segment[s] and times[s] > last_t[a]
                last_rate[a] = (u - last_u[a]) / (times[s] - last_t[a]) if same else 0.0
            else:
                last_rate[a] = phase_rate[s, a]
            unwrapped[s, a] = u
            wraps[s, a] = n
            have[a] = True
            last_u[a] = u
            last_t[a] = times[s]
            last_n[a] = n
    return unwrapped, wraps, offsets, residual, switch


def segment_starts(times: np.ndarray, scan: np.ndarray, max_gap: float) -> np.ndarray:
    """True where a solution starts a new scan or follows a gap longer than ``max_gap`` s."""
    starts = np.zeros(times.size, bool)
    if times.size:
        starts[0] = True
        starts[1:] = (np.diff(scan) != 0) | (np.diff(times) > max_gap)
    return starts
