"""A :class:`hitops.tracking.grid.TrackGrid` for tracker tests that need no Measurement Set."""

from __future__ import annotations

import numpy as np

from hitops.tracking.grid import ScanAxis, TrackGrid


def scan_grid(scan_of_time, n_bl: int) -> TrackGrid:
    """``n_bl`` baselines (all to antenna 0) at times 0, 1, 2 ... s whose tracking scan
    indices are ``scan_of_time`` (SCAN_NUMBER = index + 1)."""
    scan_of_time = np.asarray(scan_of_time, np.int64)
    n_scan = int(scan_of_time.max()) + 1 if scan_of_time.size else 0
    return TrackGrid(times=np.arange(scan_of_time.size, dtype=np.float64),
                     ant1=np.zeros(n_bl, np.int64), ant2=np.arange(1, n_bl + 1),
                     baseline_names=[f"B{b}" for b in range(n_bl)],
                     scans=ScanAxis(np.arange(1, n_scan + 1), scan_of_time))
