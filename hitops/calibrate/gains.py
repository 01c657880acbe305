"""The antenna tracker's FPT solutions as per-antenna gains, and as a CASA calibration table.

With ``--tracker antenna`` the column calibrate writes is the target DATA times
exp(-i (phi_p - phi_q)) on baseline p-q, where phi_p is R times station p's
unwrapped reference phase, minus 2 pi eps k_p where the n0 offset step gave the
station's segment an integer k_p (hitops/calibrate/n0/antenna.py).  These phi_p,
per correlation and time, are exactly what a phase-only G Jones table holds, so
CASA ``applycal`` of the table written here reproduces the column on the parallel
hands (the cross hands of the column are transferred per baseline; CASA forms
them from the receptors' gains instead).
"""

from __future__ import annotations

import math
from typing import Dict, Iterable, Optional

import numpy as np


def antenna_gain_phases(antenna_phase: np.ndarray, antenna_segment: np.ndarray,
                        scan_of_time: np.ndarray, ratio: float, eps: float,
                        offsets: Optional[Iterable[Dict]] = None, scans=None):
    """(phase, valid), both (n_time, n_ant, n_corr): the phase CASA must remove.

    antenna_phase, antenna_segment (n_ant, n_corr, n_time): the tracker's unwrapped
    per-sample reference phases and their segment ids; scan_of_time (n_time,)
    tracking-scan index of each time; ``offsets``: the offset step's entries per
    antenna (``antenna``-index ``antenna_index``, ``correlation_index``,
    ``scan_index``, ``segment``, ``k``), applied as -2 pi eps k on that segment.
    """
    phase = ratio * np.asarray(antenna_phase, dtype=np.float64)
    for a, c, where, k in _offset_cells(antenna_segment, scan_of_time, offsets):
        phase[a, c, where] -= 2.0 * math.pi * eps * k
    valid = np.isfinite(phase)
    return np.transpose(np.where(valid, phase, 0.0), (2, 0, 1)), np.transpose(valid, (2, 0, 1))


def _offset_cells(antenna_segment, scan_of_time, offsets):
    """(antenna, correlation, times, k) of every n0 entry with k != 0: the times of the
    entry's segment in its scan."""
    for entry in offsets or ():
        k = int(entry.get("k", 0))
        if k:
            a, c = int(entry["antenna_index"]), int(entry["correlation_index"])
            where = (antenna_segment[a, c] == int(entry["segment"])) & \
                (scan_of_time == int(entry["scan_index"]))
            yield a, c, where, k


def antenna_turns(antenna_phase: np.ndarray, antenna_segment: np.ndarray,
                  scan_of_time: np.ndarray, offsets: Optional[Iterable[Dict]] = None):
    """(psi, valid), both (n_time, n_ant, n_corr): each antenna's unwrapped reference
    phase with the n0 step's turns put back, psi = phi - 2 pi k on every segment the
    step gave an integer k (a per-channel transfer needs the turns, not their phase)."""
    psi = np.array(antenna_phase, dtype=np.float64)
    for a, c, where, k in _offset_cells(antenna_segment, scan_of_time, offsets):
        psi[a, c, where] -= 2.0 * math.pi * k
    valid = np.isfinite(psi)
    return np.transpose(np.where(valid, psi, 0.0), (2, 0, 1)), np.transpose(valid, (2, 0, 1))


def fringe_window(psi: np.ndarray, valid: np.ndarray, times: np.ndarray, scans: np.ndarray,
                  ratio: float, ref_freq: float, spw: int, field: int, centre_hz: float):
    """One target window of a 'Fringe Jones' table from the antennas' psi (n_time, n_ant,
    n_corr): phase R_0*psi at the window centre (wrapped: float32 keeps it to ~2e-7 rad,
    and the table holds a solution at every integration, so applycal never interpolates
    across a wrap) and delay psi / (2 pi nu_ref), so applycal gives channel k
    exp(-i R_k psi), the column's correction (hitops/calibrate/channels.py)."""
    from ..solutions.transfer import TargetWindow

    phase = np.remainder(ratio * psi + math.pi, 2.0 * math.pi) - math.pi
    return TargetWindow(spw=int(spw), field=int(field), centre_hz=float(centre_hz),
                        times=np.asarray(times, np.float64),
                        scan=np.asarray(scans, np.int32), phase=np.where(valid, phase, 0.0),
                        delay_s=np.where(valid, psi / (2.0 * math.pi * ref_freq), 0.0),
                        rate=np.zeros(psi.shape), valid=valid,
                        refant=np.full(psi.shape[0], -1, np.int32))
