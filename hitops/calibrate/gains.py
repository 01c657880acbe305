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
    for entry in offsets or ():
        k = int(entry.get("k", 0))
        if not k:
            continue
        a, c = int(entry["antenna_index"]), int(entry["correlation_index"])
        where = (antenna_segment[a, c] == int(entry["segment"])) & \
            (scan_of_time == int(entry["scan_index"]))
        phase[a, c, where] -= 2.0 * math.pi * eps * k
    valid = np.isfinite(phase)
    return np.transpose(np.where(valid, phase, 0.0), (2, 0, 1)), np.transpose(valid, (2, 0, 1))
