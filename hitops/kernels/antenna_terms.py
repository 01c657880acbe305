"""Per-antenna phase and delay terms applied to baselines.

A calibration that solves per antenna (a CASA 'Fringe Jones' table, the reference
band's solutions transferred per target channel, the calibrator step's solve) corrects
baseline p-q, correlation c with receptors (r_p, r_q), channel k as

    V_pq(k) * exp(-i [(phi_p - phi_q) + 2 pi (nu_k - nu_0)(tau_p - tau_q)]),

phi at the window's reference frequency nu_0 and tau in seconds: the form in which CASA
applycal evaluates a Fringe Jones table (channel k gets phase + 2 pi delay (nu_k - nu_c),
hitops/solutions/apply.py) and in which per-channel ratios on one reference phase are a
phase plus a delay (GUIDE section 3, "Wideband").  Being a difference of antenna terms,
every closure phase is kept.

A sample is calibrated when both antennas have a solved term for the receptor the
correlation asks of them; the others come out as zero or, with ``keep_uncalibrated``,
as they went in, and are reported so that the caller flags them.  The kernel is pure:
it never mutates its inputs; :func:`apply_antenna_terms` beside it makes the arrays
contiguous and of the kernel's types.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .wideband import cis, evenly_spaced, rotate_sample

@numba.njit(cache=True, nogil=True)
def antenna_terms_kernel(data, term_index, ant1, ant2, receptors, phase, delay_s, solved,
                         chan_offset, keep_uncalibrated):
    """Every row's correlations corrected by its two antennas' terms.

    data: (n_row, n_chan, n_corr) complex; term_index: (n_row,) int64, the row's entry on
    the terms' first axis (a time, or the row itself); ant1, ant2: (n_row,) int64;
    receptors: (n_corr, 2) int64, the receptor of ANTENNA1 and of ANTENNA2 in each
    correlation, -1 where there is none (that correlation is not calibrated); phase,
    delay_s: (n_term, n_ant, n_rec) float64, radians at nu_0 and seconds; solved:
    (n_term, n_ant, n_rec) bool; chan_offset: (n_chan,) nu_k - nu_0 in Hz.

    Returns (out, calibrated): out (n_row, n_chan, n_corr) complex64, the corrected
    samples (zero where not calibrated, or the input there with ``keep_uncalibrated``);
    calibrated (n_row, n_corr) bool.  The channel rotation is the one of
    :func:`hitops.kernels.wideband.rotate_channels`: a phasor at nu_0 stepped by the
    delay's per-channel turn on evenly spaced channels.
    """
    n_row, n_chan, n_corr = data.shape
    out = np.zeros((n_row, n_chan, n_corr), dtype=np.complex64)
    calibrated = np.zeros((n_row, n_corr), dtype=np.bool_)
    even = evenly_spaced(chan_offset)
    step_hz = (chan_offset[n_chan - 1] - chan_offset[0]) / max(n_chan - 1, 1)
    for r in range(n_row):
        t, p, q = term_index[r], ant1[r], ant2[r]
        for c in range(n_corr):
            rp, rq = receptors[c, 0], receptors[c, 1]
            if rp < 0 or rq < 0 or not (solved[t, p, rp] and solved[t, q, rq]):
                if keep_uncalibrated:
                    for k in range(n_chan):
                        out[r, k, c] = data[r, k, c]
                continue
            calibrated[r, c] = True
            rotate_sample(out, data, r, c, cis(-(phase[t, p, rp] - phase[t, q, rq])),
                          delay_s[t, p, rp] - delay_s[t, q, rq], chan_offset, even, step_hz)
    return out, calibrated


@dataclass(frozen=True)
class AntennaTerms:
    """Antenna terms of one window: what :func:`apply_antenna_terms` applies."""

    phase: np.ndarray       # (n_term, n_ant, n_rec) float64 rad at nu_0: the phase to remove
    delay_s: np.ndarray     # (n_term, n_ant, n_rec) float64 s: channel k adds 2 pi delay (nu_k - nu_0)
    solved: np.ndarray      # (n_term, n_ant, n_rec) bool


@dataclass(frozen=True)
class CorrectedRows:
    """Rows corrected by antenna terms and the samples left uncalibrated."""

    data: np.ndarray         # (n_row, n_chan, n_corr) complex64
    calibrated: np.ndarray   # (n_row, n_corr) bool


def apply_antenna_terms(data, term_index, ant1, ant2, receptors, terms: AntennaTerms,
                        chan_offset, keep_uncalibrated: bool = False) -> CorrectedRows:
    """:func:`antenna_terms_kernel` on arrays of any layout and integer type."""
    out, calibrated = antenna_terms_kernel(
        np.ascontiguousarray(data), np.ascontiguousarray(term_index, dtype=np.int64),
        np.ascontiguousarray(ant1, dtype=np.int64), np.ascontiguousarray(ant2, dtype=np.int64),
        np.ascontiguousarray(receptors, dtype=np.int64),
        np.ascontiguousarray(terms.phase, dtype=np.float64),
        np.ascontiguousarray(terms.delay_s, dtype=np.float64),
        np.ascontiguousarray(terms.solved, dtype=np.bool_),
        np.ascontiguousarray(chan_offset, dtype=np.float64), bool(keep_uncalibrated))
    return CorrectedRows(out, calibrated)
