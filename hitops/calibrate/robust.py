"""TO DELETE after the switch (issue 12): what hitops/calibrate/api.py and transfer.py still
import from here, in the old forms, on top of the new wrap tracking in :mod:`hitops.tracking`.

Wrap tracking lives in hitops/tracking/ now (docs/tracking.md); the engineer who
rebuilds api.py and transfer.py imports from there and deletes this module.
Nothing else may import it.
"""

from __future__ import annotations

from ..errors import InputError
from ..geometry import station_sin_elevation  # noqa: F401  (api.py)
from ..tracking.factory import new_tracker
from ..tracking.grid import gather_grid, grid_positions  # noqa: F401  (api.py)
from ..tracking.options import ANTENNA_TRACK_HALF_WINDOW  # noqa: F401  (api.py)
from ..tracking.options import check_options as _check_numbers
from ..tracking.options import setup_tracking as _setup_tracking
from ..tracking.options import sigma_source  # noqa: F401  (api.py)
from ..tracking.state import SEGMENT_KEY, apply_segment_offsets  # noqa: F401  (api.py)

TRACKER_CHOICES = ("count", "smooth", "antenna")
JUMP_ACTIONS = ("segment", "flag")


def check_options(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                  jump_window, jump_action, solve_half_window) -> None:
    """The old check: the choices (the Python API has no schema check yet), then the numbers."""
    if tracker not in TRACKER_CHOICES:
        raise InputError(f"--tracker: unknown wrap tracker {tracker!r}; choose one of "
                         f"{', '.join(TRACKER_CHOICES)} (docs/tracking.md)")
    _check_numbers(half_window=half_window, coherence_time=coherence_time, snr=snr,
                   max_gap=max_gap, jump_threshold=jump_threshold, jump_window=jump_window,
                   solve_half_window=solve_half_window)
    if jump_action not in JUMP_ACTIONS:
        raise InputError(f"--jump-action {jump_action!r}: choose segment (start a new, reported "
                         "segment at each jump) or flag (flag the reference samples from each "
                         "jump to the end of its segment)")


def setup_tracking(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                   jump_window, jump_action, refant, solve_half_window, dt, antenna_names,
                   snr_from: str, elevation_scaling: bool = False):
    """The old signature: api.py sets ``setup.sin_elevation`` itself afterwards."""
    setup = _setup_tracking(tracker, half_window, coherence_time, snr, max_gap, jump_threshold,
                            jump_window, jump_action, refant, solve_half_window, dt,
                            antenna_names, snr_from)
    setup.elevation_scaling = bool(elevation_scaling)
    return setup


class ReferenceTracker:
    """The old class: the new smooth/antenna tracker, ``track`` returning the old 4-tuple."""

    def __init__(self, setup, match, corr_names, n_ant, antenna_names, workers=0,
                 sin_elevation=None):
        self._tracker = new_tracker(setup.tracker, match, corr_names, setup, n_ant,
                                    antenna_names, workers, sin_elevation)

    def __getattr__(self, name):
        return getattr(self._tracker, name)

    def track(self, t_lo, t0, t1, t_hi, vis, valid, sigma):
        return self._tracker.track(t_lo, t0, t1, t_hi, vis, valid, sigma).as_tuple()


def segment_offset_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid):
    """The old name of :func:`hitops.calibrate.lattice.segment_run_sums` (transfer.py)."""
    from .lattice import segment_run_sums
    return segment_run_sums(keys, tgt_phase, phasor, calibrated, off_phase, off_valid)
