"""The calibrator's side of the step: per calibrator scan and window, its FPT output summed
per baseline and channel (divided by the calibrator's model), each scan's integer of
2 pi R_k m found from its delay and removed, then antenna phases and delays solved.

Why integers per scan: every scan's reference wrap count starts afresh (the count
tracker restarts at each tracking scan; the slews between fields are too long to carry
it across: docs/solutions.md, "The instrumental term"), so each scan of each baseline
carries 2 pi R_k m with its own integer m.  Across the window that term is a delay
m / nu_ref (11.6 ps per wrap at 86 GHz) and a phase 2 pi R_0 m at the centre, while the
instrumental delay moves slowly from scan to scan: the scan-to-scan changes of each
baseline's delay give m (hitops/kernels/phase_ref.py: ``scan_integers``).  Removed, what
is left on each baseline is the instrumental term plus one integer of the first scan,
constant over the track: the antenna solve takes the first and the per-baseline residual
(what no antenna term absorbs) the second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from ...errors import InputError
from ...kernels.phase_ref import (antenna_phasors, model_residuals,
                                  phase_and_delay, scan_integers)

#: a calibrator scan's integer is taken when the second-nearest candidate lies at least
#: this much further from the measured (delay in wraps, phase in PHASE_PER_WRAP) than the
#: nearest (noise-free: >= 2.2 after the first cycle, kernels/phase_ref.py)
MIN_CALIBRATOR_MARGIN = 0.5

#: iterations of the per-channel antenna phase solve (converged to < 1e-6 rad on the
#: noise-free pairs of tests/test_phase_referencing.py well before this)
SOLVE_ITERATIONS = 60


@dataclass(frozen=True)
class WindowFrame:
    """What one target window's frequencies are to the step, as the transfer used them:
    nu_0 (its phase and the solutions refer to it), each channel's nu_k - nu_0 and R_k,
    and R_0 = nu_0 / nu_ref."""

    centre: float
    chan_offset: np.ndarray
    ratios: np.ndarray
    ratio: float

    @property
    def wrap_delay(self) -> float:
        """The delay of one reference wrap on the target band: R_0 / nu_0 = 1 / nu_ref (s)."""
        return self.ratio / self.centre

    @classmethod
    def of_group(cls, group) -> "WindowFrame":
        """The frame of a group pair: its ChannelPlan, or its one ratio on one channel."""
        if group.channels is not None:
            plan = group.channels
            return cls(plan.tgt_centre, plan.chan_offset, plan.ratios, plan.ratio)
        freq = np.asarray(group.pair.tgt.chan_freq, float)
        return cls(float(group.pair.tgt.freq), freq - group.pair.tgt.freq,
                   freq * (group.ratio / group.pair.tgt.freq), float(group.ratio))


@dataclass(frozen=True)
class ScanSolution:
    """One calibrator scan's antenna phases and delays in one spectral window."""

    scan: int
    time: float                  # s, mean TIME of the scan's rows
    phase: np.ndarray            # (n_ant, n_hand) rad at the window's centre
    delay: np.ndarray            # (n_ant, n_hand) s
    valid: np.ndarray            # (n_ant, n_hand) bool


@dataclass(frozen=True)
class CalibratorIntegers:
    """Each calibrator scan's integer per baseline and hand, and how each was decided."""

    integers: np.ndarray         # (n_scan, n_bl, n_hand) int64
    margin: np.ndarray           # (n_scan, n_bl, n_hand) wraps from the rounding boundary
    rule: str                    # "delay" (per scan from the slope) or "carried"


@dataclass(frozen=True)
class WindowSolution:
    """Every calibrator scan of one target spectral window, and what the window is."""

    ddid: int
    spw: int
    freq: float                  # nu_0 (Hz)
    hands: Tuple[str, ...]       # the receptor letters of the parallel hands ('R', 'L')
    refant: int
    scans: List[ScanSolution]
    integers: CalibratorIntegers
    # what the antenna model leaves per calibrator baseline (ant1 * n_ant + ant2 in
    # ``baselines``), channel and hand, summed over every scan: its phase is removed
    # from the target's same baseline (hitops/kernels/phase_ref.py: model_residuals)
    baselines: np.ndarray        # (n_bl,) int64
    residual: np.ndarray         # (n_bl, n_chan, n_hand) complex128

    def at(self, times: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(phase, delay) (n_time, n_ant, n_hand) interpolated at ``times``; solved
        (n_ant, n_hand): antennas with at least one valid scan."""
        t = np.array([s.time for s in self.scans])
        phase = np.stack([s.phase for s in self.scans])
        delay = np.stack([s.delay for s in self.scans])
        valid = np.stack([s.valid for s in self.scans])
        n_ant, n_hand = phase.shape[1:]
        out_phase = np.zeros((times.size, n_ant, n_hand))
        out_delay = np.zeros_like(out_phase)
        for a in range(n_ant):
            for h in range(n_hand):
                ok = valid[:, a, h]
                if ok.any():
                    # the phase moves slowly from scan to scan: unwrap it in time
                    out_phase[:, a, h] = np.interp(times, t[ok], np.unwrap(phase[ok, a, h]))
                    out_delay[:, a, h] = np.interp(times, t[ok], delay[ok, a, h])
        return out_phase, out_delay, valid.any(axis=0)


def model_divided(vis: np.ndarray, model: Optional[np.ndarray]) -> np.ndarray:
    """The calibrator's visibilities divided by its model's phase (gaincal's and
    fringefit's use of MODEL_DATA; zeros were refused before: step.check_model)."""
    if model is None:
        return vis
    size = np.abs(model)
    return vis * (np.conj(model) / np.where(size > 0, size, 1.0))


def calibrator_integers(times: np.ndarray, sums: np.ndarray, counts: np.ndarray,
                        frame: WindowFrame) -> CalibratorIntegers:
    """Each scan's integer per baseline and hand from the scan-to-scan change of the
    baseline's phase and delay across the window (kernels/phase_ref.py: scan_integers)."""
    n_scan, n_bl, _, n_hand = sums.shape
    phase = np.zeros((n_scan, n_bl, n_hand))
    delay = np.zeros((n_scan, n_bl, n_hand))
    valid = np.zeros((n_scan, n_bl, n_hand), bool)
    for j in range(n_scan):
        # a baseline's phase and delay: phase_and_delay with baselines for antennas
        phase[j], delay[j], valid[j] = phase_and_delay(sums[j], counts[j] > 0,
                                                       frame.chan_offset)
    m, margin = scan_integers(times, phase.reshape(n_scan, -1), delay.reshape(n_scan, -1),
                              valid.reshape(n_scan, -1), frame.wrap_delay, frame.ratio)
    return CalibratorIntegers(m.reshape(n_scan, n_bl, n_hand),
                              margin.reshape(n_scan, n_bl, n_hand), "delay")


def check_decided(integers: CalibratorIntegers, scan_numbers: List[int], labels: List[str],
                  cal_name: str, spw: int) -> None:
    """Every calibrator scan's integer clear of the next candidate, or one line naming the
    scans: a wrong integer there would move every target scan near it."""
    unclear = np.isfinite(integers.margin) & (integers.margin < MIN_CALIBRATOR_MARGIN)
    if not unclear.any():
        return
    scans = sorted({scan_numbers[j] for j in np.flatnonzero(unclear.any(axis=(1, 2)))})
    worst = sorted({labels[b] for b in np.flatnonzero(unclear.any(axis=(0, 2)))})
    raise InputError(f"--calibrator-field {cal_name}: too faint for each scan's integer in "
                     f"spectral window {spw}: calibrator scan(s) {', '.join(map(str, scans))} "
                     f"on {', '.join(worst)} leave two integers nearly as likely (margin "
                     f"{float(integers.margin[unclear].min()):.2f} < {MIN_CALIBRATOR_MARGIN}); "
                     "use a brighter calibrator, longer calibrator scans or a wider window")


def without_integers(sums: np.ndarray, integers: np.ndarray, ratios: np.ndarray) -> np.ndarray:
    """Scan sums times exp(-i 2 pi R_k m): (n_scan, n_bl, n_chan, n_hand)."""
    turns = integers[:, :, None, :] * ratios[None, None, :, None]
    return sums * np.exp(-2j * np.pi * (turns - np.round(turns)))


def solve_window(scans, times, sums, counts, ant1: np.ndarray, ant2: np.ndarray,
                 frame: WindowFrame, integers: CalibratorIntegers, refant: int, n_ant: int,
                 window: Tuple[int, int, Tuple[str, ...]]) -> WindowSolution:
    """Antenna phases and delays per calibrator scan from the sums with each scan's
    integer removed; ``ant1``, ``ant2``: each calibrator baseline's antennas (the sums'
    second axis); ``window``: (ddid, spw, hands)."""
    clean = without_integers(sums, integers.integers, frame.ratios)
    solutions, residual = [], 0j
    for j, scan in enumerate(scans):
        g, solved = antenna_phasors(clean[j], counts[j], ant1, ant2, n_ant, refant,
                                    SOLVE_ITERATIONS)
        phase, delay, valid = phase_and_delay(g, solved, frame.chan_offset)
        residual = residual + model_residuals(clean[j], counts[j], ant1, ant2, phase,
                                              delay, valid, frame.chan_offset)
        solutions.append(ScanSolution(int(scan), float(times[j]), phase, delay, valid))
    ddid, spw, hands = window
    return WindowSolution(ddid, spw, frame.centre, hands, refant, solutions, integers,
                          ant1.astype(np.int64) * n_ant + ant2, residual)
