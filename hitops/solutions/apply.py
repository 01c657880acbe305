"""A target-band Fringe Jones table evaluated at the target's times, as CASA applycal does.

``hitops calibrate --reference-table`` writes the target column from the same
:class:`~hitops.solutions.transfer.TargetWindow` rows that the ``--caltable`` table
holds, evaluated the way CASA applycal (interp 'linear') evaluates a Fringe Jones table,
so that applycal of the table reproduces the column (tests/test_calibrate_reference_table.py
checks it with the real applycal).  CASA's rules, from its source
(``CTRateAwareTimeInterp1::applyPhaseRate`` and ``FringeJones::calcAllJones`` in
``synthesis/MeasurementComponents/FringeJones.cc``, as held in ARDG-NRAO/LibRA):

* between two solutions t0 < t < t1, each solution's phase is carried to t with its own
  rate, phi_j + 2*pi*rate_j*nu_c*(t - t_j) (nu_c the table's CHAN_FREQ of the window),
  and the two phasors are averaged with the linear weights (t1 - t)/(t1 - t0) and
  (t - t0)/(t1 - t0); the phase is the argument of that mean;
* the delay is interpolated linearly in time;
* before the first and after the last solution, the nearest one carried with its rate;
* channel k then gets phase + 2*pi*delay*(nu_k - nu_c);
* with applycal's default ``gainfield=''`` the solutions of every field of a window form
  one time series: a row next to a scan boundary is interpolated between the last
  solution of its field's scan and the first of the next scan, whichever field that
  observed (:func:`all_fields`).  Measured on two fields in alternating scans: 3 % of the
  samples differed by more than 0.01 rad from applycal when each field was interpolated
  alone.

The parameters are used as the table stores them (float32), so a table solved at every
integration reproduces the column to float32 rounding.  A sample whose bracketing
solutions include a flagged one gets no correction (applymode 'calflag' flags it).
The kernel is pure: it never mutates its inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ..kernels.antenna_terms import AntennaTerms, CorrectedRows, apply_antenna_terms
from .transfer import TargetWindow

TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True)
def rate_aware_series(sol_times, phase, delay_s, rate, valid, centre_hz, times):
    """One antenna and receptor: (phase at nu_c, delay s, ok) at each of ``times``.

    sol_times (n_sol,) ascending; phase, delay_s, rate (n_sol,) float64; valid (n_sol,)
    bool; times (n,) float64.  Returns float64 (n,), float64 (n,), bool (n,).
    """
    n = times.size
    n_sol = sol_times.size
    out_phase = np.zeros(n)
    out_delay = np.zeros(n)
    ok = np.zeros(n, dtype=np.bool_)
    if n_sol == 0:
        return out_phase, out_delay, ok
    for i in range(n):
        t = times[i]
        j = np.searchsorted(sol_times, t)
        if j < n_sol and sol_times[j] == t:
            lo, hi = j, j
        elif j == 0:
            lo, hi = 0, 0
        elif j == n_sol:
            lo, hi = n_sol - 1, n_sol - 1
        else:
            lo, hi = j - 1, j
        if not (valid[lo] and valid[hi]):
            continue
        p_lo = phase[lo] + TWO_PI * rate[lo] * centre_hz * (t - sol_times[lo])
        if lo == hi:
            out_phase[i] = p_lo
            out_delay[i] = delay_s[lo]
        else:
            p_hi = phase[hi] + TWO_PI * rate[hi] * centre_hz * (t - sol_times[hi])
            w = (sol_times[hi] - t) / (sol_times[hi] - sol_times[lo])
            re = w * math.cos(p_lo) + (1.0 - w) * math.cos(p_hi)
            im = w * math.sin(p_lo) + (1.0 - w) * math.sin(p_hi)
            out_phase[i] = math.atan2(im, re)
            out_delay[i] = w * delay_s[lo] + (1.0 - w) * delay_s[hi]
        ok[i] = True
    return out_phase, out_delay, ok


@dataclass(frozen=True)
class AntennaGains:
    """One target window's antenna terms at a set of times (applycal's evaluation)."""

    centre_hz: float      # nu_c, the table's CHAN_FREQ of the window: the terms' nu_0
    terms: AntennaTerms   # (n_time, n_ant, n_rec) phases at centre_hz, delays, solved


def as_stored(window: TargetWindow):
    """phase, delay (s) and rate as the written table holds them (FPARAM is float32, delay in ns)."""
    phase = window.phase.astype(np.float32).astype(np.float64)
    delay = (window.delay_s * 1e9).astype(np.float32).astype(np.float64) * 1e-9
    rate = window.rate.astype(np.float32).astype(np.float64)
    return phase, delay, rate


def all_fields(windows) -> dict:
    """{spectral window: one TargetWindow holding every field's solutions in time order}."""
    import dataclasses

    merged = {}
    for spw in sorted({w.spw for w in windows}):
        parts = [w for w in windows if w.spw == spw]
        if len(parts) == 1:
            merged[spw] = parts[0]
            continue
        times = np.concatenate([w.times for w in parts])
        order = np.argsort(times, kind="stable")

        def cat(name):
            return np.concatenate([getattr(w, name) for w in parts])[order]

        merged[spw] = dataclasses.replace(parts[0], field=-1, times=times[order], scan=cat("scan"),
                                          phase=cat("phase"), delay_s=cat("delay_s"),
                                          rate=cat("rate"), valid=cat("valid"), refant=cat("refant"))
    return merged


def gains_at(window: TargetWindow, times: np.ndarray) -> AntennaGains:
    """The window's antenna phases and delays at ``times``, as applycal evaluates its table."""
    phase, delay, rate = as_stored(window)
    times = np.ascontiguousarray(times, dtype=np.float64)
    n_ant, n_rec = phase.shape[1], phase.shape[2]
    shape = (times.size, n_ant, n_rec)
    out_phase, out_delay, ok = np.zeros(shape), np.zeros(shape), np.zeros(shape, bool)
    sol_times = np.ascontiguousarray(window.times, dtype=np.float64)
    for ant in range(n_ant):
        for rec in range(n_rec):
            p, d, k = rate_aware_series(sol_times, np.ascontiguousarray(phase[:, ant, rec]),
                                        np.ascontiguousarray(delay[:, ant, rec]),
                                        np.ascontiguousarray(rate[:, ant, rec]),
                                        np.ascontiguousarray(window.valid[:, ant, rec]),
                                        float(window.centre_hz), times)
            out_phase[:, ant, rec], out_delay[:, ant, rec], ok[:, ant, rec] = p, d, k
    return AntennaGains(float(window.centre_hz), AntennaTerms(out_phase, out_delay, ok))


def apply_window(window: TargetWindow, time, ant1, ant2, receptors, data,
                 chan_freq) -> CorrectedRows:
    """Target rows of one window corrected as applycal applies the table written from
    ``window``: each row's antenna terms at its TIME, gathered onto its baseline and
    correlations (hitops/kernels/antenna_terms.py); samples without a solution on either
    side come out zero, reported as not calibrated.

    time, ant1, ant2: (n_row,); receptors: (n_corr, 2) of ANTENNA1, ANTENNA2 per
    correlation; data: (n_row, n_chan, n_corr); chan_freq: (n_chan,) Hz.
    """
    times, time_index = np.unique(time, return_inverse=True)
    gains = gains_at(window, times)
    # a T Jones source: one receptor for both hands
    receptors = np.minimum(receptors, gains.terms.phase.shape[2] - 1)
    return apply_antenna_terms(data, time_index.ravel(), ant1, ant2, receptors, gains.terms,
                               np.asarray(chan_freq, float) - gains.centre_hz)
