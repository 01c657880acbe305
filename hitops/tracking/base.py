"""The one interface of the three reference-band wrap trackers (count, smooth, antenna).

A calibrate run reads the reference band chunk by chunk.  For chunk [t0, t1)
of the union time axis the pipeline asks the tracker which times it needs
(:meth:`WrapTracker.extended`: ``context`` samples either side for the
smooth and antenna trackers, none for count), reads them onto a
(baseline, correlation, time) grid and calls :meth:`WrapTracker.track`, which
returns a :class:`Tracked` for [t0, t1) and moves the tracker's ``state`` on to
the next chunk.  Only ``track`` changes the state, and chunks must come in
time order: that is what makes the counts independent of the chunk size.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class Tracked:
    """What a tracker gives the transfer for one chunk [t0, t1) (arrays (n_bl, n_corr, t1-t0)).

    ref_wraps: int64 reference wrap counts (wrapped phase - 2 pi n = unwrapped);
    ref_exclude: bool reference samples to leave out (--jump-action flag), or None;
    segment_keys: int64 segment key per sample (scan index * SEGMENT_KEY + segment,
    -1 where invalid; the per-segment n0 step), or None (count: per scan);
    ref_model: float64 antenna mode's unwrapped model phase of each baseline, NaN
    where not modelled, or None (the baseline's own phase is transferred).
    """

    ref_wraps: np.ndarray
    ref_exclude: Optional[np.ndarray] = None
    segment_keys: Optional[np.ndarray] = None
    ref_model: Optional[np.ndarray] = None

    def as_tuple(self):
        return self.ref_wraps, self.ref_exclude, self.segment_keys, self.ref_model


class WrapTracker(ABC):
    """Reference wrap tracking carried across time chunks.

    Attributes: ``name`` ('count', 'smooth' or 'antenna'); ``context``
    (reference samples needed each side of a chunk); ``state`` (what the next
    chunk continues from); ``stats`` (:class:`hitops.tracking.state.Stats`);
    ``antenna_phase`` / ``antenna_segment`` ((n_ant, n_corr, n_time) unwrapped
    antenna phases and their segments, antenna mode only, else None).
    """

    name: str = ""
    context: int = 0
    antenna_phase: Optional[np.ndarray] = None
    antenna_segment: Optional[np.ndarray] = None

    @abstractmethod
    def extended(self, t0: int, t1: int):
        """(t_lo, t_hi): the times to read for chunk [t0, t1)."""

    @abstractmethod
    def track(self, t_lo: int, t0: int, t1: int, t_hi: int, vis, valid, sigma) -> Tracked:
        """Counts of chunk [t0, t1) from the reference grid of [t_lo, t_hi).

        vis (complex), valid (bool), sigma (float64 or None):
        (n_bl, n_corr, t_hi - t_lo), baselines in the order of ``match``.
        """

    @abstractmethod
    def report(self, times: np.ndarray) -> dict:
        """The JSON report's ``tracking`` entry after the last chunk."""


def scan_runs(scan_of_time: np.ndarray):
    """(start, stop, scan) of each run of equal scan index (a tracker restarts at each)."""
    if scan_of_time.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(scan_of_time)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [scan_of_time.size]])
    return [(int(a), int(b), int(scan_of_time[a])) for a, b in zip(starts, stops)]
