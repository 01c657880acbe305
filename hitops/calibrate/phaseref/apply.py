"""The target's side of the step: the calibrator's antenna terms interpolated onto the
target's rows and removed, the per-baseline residual with them, then each target scan's
own integer of 2 pi R_k j found from what is left and removed.

After the calibrator's terms, a target scan keeps 2 pi R_k j (its wrap count started
afresh, as every scan's does) plus what the interpolation misses: its delay across the
window, j / nu_ref, is j (the source's own structure aside: a point-like target, or one
whose delay across the window is well under half a wrap, 5.8 ps at 86 GHz).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from ...kernels.antenna_terms import AntennaTerms, apply_antenna_terms
from ...kernels.phase_ref import phase_and_delay, scan_integers, times_factors
from ...kernels.wideband import rotate_channels
from .solve import WindowFrame, WindowSolution

#: a target series' offset is taken when its mean delay left lies within
#: 0.5 - MIN_TARGET_MARGIN wraps of a whole number (noise-free scenes: within 0.08 wraps,
#: measured on tests/test_sfpr.py's), and a scan's step from its neighbours when the
#: next candidate lies MIN_STEP_MARGIN further (kernels/phase_ref.py's units); a scan or
#: series that misses either is flagged on its baseline and hand rather than guessed
MIN_TARGET_MARGIN = 0.2
MIN_STEP_MARGIN = 0.5


@dataclass(frozen=True)
class TargetIntegers:
    """Each target scan's integer per baseline and hand, and its decision margin."""

    scans: np.ndarray            # (n_scan,) tracking scan ids
    baselines: np.ndarray        # (n_bl,) ant1 * n_ant + ant2
    integers: np.ndarray         # (n_scan, n_bl, n_hand) int64
    margin: np.ndarray           # (n_scan, n_bl, n_hand) wraps from the rounding boundary
    #                              (the series' offset; 0 where the scan's step was unclear)
    valid: np.ndarray            # (n_scan, n_bl, n_hand) bool

    @property
    def undecided(self) -> np.ndarray:
        """(n_scan, n_bl, n_hand) measured, but too far from every integer to take one."""
        return self.valid & (self.margin < MIN_TARGET_MARGIN)


def baseline_factors(solution: WindowSolution, ant1, ant2, corr_hands, n_ant: int):
    """(n_row, n_chan, n_corr) complex64: exp(-i x the calibrator's model residual phase)
    of each row's baseline on its parallel hands; 1 for cross hands and baselines the
    calibrator did not observe."""
    n_chan = solution.residual.shape[1]
    out = np.ones((ant1.size, n_chan, corr_hands.shape[0]), np.complex64)
    code = ant1.astype(np.int64) * n_ant + ant2
    pos = np.minimum(np.searchsorted(solution.baselines, code), solution.baselines.size - 1)
    seen = solution.baselines[pos] == code
    for c, (h1, h2) in enumerate(corr_hands):
        if h1 < 0 or h1 != h2:
            continue
        res = solution.residual[pos[seen], :, h1]
        out[seen, :, c] = np.where(np.abs(res) > 0, np.conj(res) / np.maximum(np.abs(res), 1e-300),
                                   1.0)
    return out


def apply_chunk(set_rows, tx, column: str, rows, solution: WindowSolution,
                corr_hands: np.ndarray, frame: WindowFrame,
                n_ant: int) -> Tuple[int, np.ndarray, np.ndarray]:
    """The interpolated correction applied to one chunk's target rows (``rows``: a
    :class:`.passes.RowsOf`) through the transaction's own write path: the antenna terms by
    the one kernel that applies per-antenna terms to baselines (kernels/antenna_terms.py;
    samples of an antenna without a solution kept as they are and flagged), then the
    calibrator's per-baseline residual.  Returns (rows flagged, the rows' flags now, the
    rows as corrected)."""
    phase, delay, solved = solution.at(rows.time)
    terms = AntennaTerms(phase, delay, np.broadcast_to(solved, phase.shape))
    read = set_rows.reader(rows.rows)
    corrected = apply_antenna_terms(read(column), np.arange(rows.rows.size), rows.ant1,
                                    rows.ant2, corr_hands, terms, frame.chan_offset,
                                    keep_uncalibrated=True)
    rotated = times_factors(corrected.data, np.broadcast_to(baseline_factors(
        solution, rows.ant1, rows.ant2, corr_hands, n_ant), corrected.data.shape))
    flags = tx.flags_now(set_rows, rows.rows)
    ok = corrected.calibrated
    n_flagged, new_flag = 0, None
    if not ok.all():
        flags = new_flag = flags | ~ok[:, None, :]
        n_flagged = int((~ok).any(axis=1).sum())
    tx.restage(rows.rows, {column: rotated}, new_flag)
    return n_flagged, flags, rotated


def target_integers(scans: np.ndarray, times: np.ndarray, left: np.ndarray,
                    n_left: np.ndarray, frame: WindowFrame, n_ant: int) -> TargetIntegers:
    """Each target scan's integer per baseline and hand from what the calibrator's terms
    left on it: from scan to scan as on the calibrator (its phase and delay across the
    window continue: kernels/phase_ref.scan_integers; a compact target's own phase moves
    slowly between its scans), then one offset per series, the nearest whole number of
    wraps to the mean delay left over all its scans (its noise shrinks with their number).
    ``times``: each scan's mean time."""
    n_bl, n_hand = n_ant * n_ant, left.shape[2]
    phase, delay, valid = phase_and_delay(left, n_left > 0, frame.chan_offset)
    shape = (scans.size, n_bl * n_hand)
    phase, delay, valid = phase.reshape(shape), delay.reshape(shape), valid.reshape(shape)
    steps, step_margin = scan_integers(times, phase, delay, valid, frame.wrap_delay,
                                       frame.ratio)
    unclear = np.isfinite(step_margin) & (step_margin < MIN_STEP_MARGIN)
    # the offset from the scans whose step is clear (an unclear one is flagged anyway)
    counted = valid & ~unclear
    left_wraps = np.where(counted, delay / frame.wrap_delay - steps, 0.0)
    mean = left_wraps.sum(axis=0) / np.maximum(counted.sum(axis=0), 1)
    offset = np.round(mean)
    integers = np.where(valid, steps + offset[None, :], 0).astype(np.int64)
    margin = np.broadcast_to(0.5 - np.abs(mean - offset), shape)
    out = (scans.size, n_bl, n_hand)
    return TargetIntegers(scans, np.arange(n_bl), integers.reshape(out),
                          np.where(unclear, 0.0, margin).reshape(out), valid.reshape(out))


def row_counts(scan_of_row: np.ndarray, scans: np.ndarray, bl_of_row: np.ndarray,
               integers: np.ndarray, corr_hands: np.ndarray) -> np.ndarray:
    """(n_row, n_corr): each row's value on its parallel hands (0 on cross hands), from
    ``integers`` (n_scan, n_bl, n_hand) indexed by the row's scan and baseline."""
    j = np.searchsorted(scans, scan_of_row)
    out = np.zeros((scan_of_row.size, corr_hands.shape[0]), integers.dtype)
    for c, (h1, h2) in enumerate(corr_hands):
        if h1 >= 0 and h1 == h2:
            out[:, c] = integers[j, bl_of_row, h1]
    return out


def remove_integers(set_rows, tx, column: str, rows: np.ndarray, counts: np.ndarray,
                    frame: WindowFrame, block: int) -> None:
    """Rows times exp(-i 2 pi R_k n), n per row and correlation (``counts``), as a phase at
    nu_0 and a delay n / nu_ref, the per-channel transfer's own form; rows with n = 0
    on every correlation are not touched."""
    moved = (counts != 0).any(axis=1)
    rows, counts = rows[moved], counts[moved]
    for start in range(0, rows.size, block):
        part, n = rows[start:start + block], counts[start:start + block]
        read = set_rows.reader(part)
        turns = n * frame.ratio
        phasor = np.exp(-2j * np.pi * (turns - np.round(turns)))
        tx.restage(part, {column: rotate_channels(read(column), phasor, n * frame.wrap_delay,
                                                  frame.chan_offset)})


def flag_rows(set_rows, tx, rows: np.ndarray, mask: np.ndarray, block: int) -> int:
    """Flags of ``rows`` raised on the correlations of ``mask`` (n_row, n_corr) bool,
    staged for the commit; the number of rows touched."""
    hit = mask.any(axis=1)
    rows, mask = rows[hit], mask[hit]
    for start in range(0, rows.size, block):
        part = rows[start:start + block]
        tx.restage(part, {}, tx.flags_now(set_rows, part) | mask[start:start + block, None, :])
    return int(rows.size)
