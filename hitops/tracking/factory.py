"""The tracker of a calibrate run, by name: the pipeline calls all three the same way."""

from __future__ import annotations

from .antenna import AntennaTracker
from .base import WrapTracker
from .count import CountTracker
from .grid import TrackGrid
from .smooth import SmoothTracker

#: tracker classes by ``--tracker`` name (the schema enforces the choice)
TRACKER_CLASSES = {"count": CountTracker, "smooth": SmoothTracker, "antenna": AntennaTracker}


def new_tracker(name: str, grid: TrackGrid, corr_names, setup=None, n_ant: int = 0, antenna_names=(),
                workers: int = 0, sin_elevation=None) -> WrapTracker:
    """A fresh tracker (empty state) of ``--tracker name`` on ``grid`` (baselines, times, scans).

    ``setup``: the :class:`hitops.tracking.options.TrackingSetup` (None for count);
    ``workers``: threads for the smooth series (0: one per core; 1 on a cluster,
    where the cores belong to the workers).
    """
    return TRACKER_CLASSES[name](grid, corr_names, setup=setup, n_ant=n_ant,
                                 antenna_names=antenna_names, workers=workers,
                                 sin_elevation=sin_elevation)
