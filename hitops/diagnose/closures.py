"""Closure phases straight from Measurement Set rows (any storage order, any gaps).

Used to check what a calibration did to a source's structure: closure phases of
the target band before and after must agree where the calibration is
antenna-based (hitops calibrate --tracker antenna), and differ by R times the
reference band's where it transfers baseline phases.
"""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np


def row_closures(time: np.ndarray, ant1: np.ndarray, ant2: np.ndarray, vis: np.ndarray,
                 valid: np.ndarray) -> Dict[Tuple[float, int, int, int], float]:
    """{(time, p, q, r): phi_pq + phi_qr - phi_pr} over every triangle of valid rows.

    time, ant1, ant2 (n_row,); vis (n_row,) complex (phases taken in float64);
    valid (n_row,) bool.  Times are rounded to 0.1 s to group the rows of one
    integration; p < q < r are antenna indices.
    """
    phase = np.angle(np.asarray(vis).astype(np.complex128))
    by_time: Dict[float, Dict[Tuple[int, int], float]] = {}
    for i in np.flatnonzero(valid):
        by_time.setdefault(round(float(time[i]), 1), {})[(int(ant1[i]), int(ant2[i]))] = phase[i]
    out = {}
    for t, bls in by_time.items():
        ants = sorted({a for bl in bls for a in bl})
        for i, p in enumerate(ants):
            for j, q in enumerate(ants[i + 1:], i + 1):
                for r in ants[j + 1:]:
                    if (p, q) in bls and (q, r) in bls and (p, r) in bls:
                        out[(t, p, q, r)] = bls[(p, q)] + bls[(q, r)] - bls[(p, r)]
    return out


def closure_change(before: Dict, after: Dict) -> np.ndarray:
    """|wrapped difference| (rad) of two closure sets over their common keys."""
    keys = sorted(before.keys() & after.keys())
    diff = np.array([after[k] - before[k] for k in keys])
    return np.abs((diff + np.pi) % (2 * np.pi) - np.pi)
