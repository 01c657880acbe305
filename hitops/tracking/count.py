"""The paper's wrap counter (``--tracker count``): a step > pi between consecutive samples.

Paper (fpt-arbitrary-ratios.tex, "Phase-wrap counting"): a wrapped phase in
[-pi, pi) that crosses the boundary from the -pi side jumps by +2*pi, so the
wrap count n(t) goes up by one; crossing from the +pi side it goes down by
one.  A step of magnitude > pi between consecutive samples is taken as a wrap
(valid while the Itoh condition holds: true steps stay below pi).

:func:`count_wraps` is the numba kernel on one series; :func:`count_scans`
runs it over a (baseline, correlation, time) chunk, restarting at each scan and
continuing across chunks through a :class:`Carry` (the last valid sample of
each series and its count), so the counts do not depend on the chunk size;
:class:`CountTracker` is the same behind the :class:`~hitops.tracking.base.WrapTracker`
interface.  It needs no context: one sample is carried instead.  In a calibrate
run it needs no grid either: each baseline batch's transfer task counts its own
phases from its part of the carry (:class:`CountedWraps`), and the tracker takes
the carry and the wrap events back (:meth:`CountTracker.absorb`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .base import ChunkTracking, BatchWraps, ResolvedWraps, Tracked, WrapTracker
from .grid import TrackGrid
from .state import Stats


@numba.njit(cache=True, nogil=True, inline="always")
def wrap_step(count, last, phase):
    """The count after a valid sample ``phase`` that follows the valid sample ``last``."""
    step = phase - last
    if step > math.pi:
        return count + 1
    if step < -math.pi:
        return count - 1
    return count


@numba.njit(cache=True, nogil=True)
def count_wraps(ref_phase, valid):
    """Cumulative wrap count n(t) of ``ref_phase`` (radians, wrapped).

    Starts at 0; a step > pi between consecutive *valid* samples is a wrap
    (+1 when the phase jumps up, i.e. crossed from the -pi side, -1 when it
    jumps down).  Invalid or non-finite samples take no part and carry the
    previous count.
    """
    n_time = ref_phase.shape[0]
    wraps = np.zeros(n_time, dtype=np.int64)
    count = 0
    have_last = False
    last = 0.0
    for t in range(n_time):
        phase = ref_phase[t]
        if valid[t] and math.isfinite(phase):
            if have_last:
                count = wrap_step(count, last, phase)
            last = phase
            have_last = True
        wraps[t] = count
    return wraps


@numba.njit(cache=True, nogil=True)
def count_chunk(phase, valid, scan_of_time, last_phase, has_last, count, last_scan):
    """:func:`count_wraps` on every (baseline, correlation) series of a chunk, restarting at
    each scan and continuing the carried state (``last_phase``, ``has_last``, ``count``
    (n_bl, n_corr), the previous chunk's ``last_scan``) in the chunk's first scan.

    Returns the counts (n_bl, n_corr, n_time) int64 and the state after the chunk
    (last_phase, has_last, count; copies: the inputs are not changed).  A series that saw
    no valid sample in its last scan keeps its carried state when that scan is the
    carried one and the chunk's only scan, and starts afresh otherwise.
    """
    n_bl, n_corr, n_time = phase.shape
    wraps = np.zeros((n_bl, n_corr, n_time), dtype=np.int64)
    new_phase, new_has, new_count = last_phase.copy(), has_last.copy(), count.copy()
    if n_time == 0:
        return wraps, new_phase, new_has, new_count
    continues = scan_of_time[0] == last_scan
    last_start = 0
    for t in range(1, n_time):
        if scan_of_time[t] != scan_of_time[t - 1]:
            last_start = t
    for b in range(n_bl):
        for c in range(n_corr):
            # the carried sample goes first, as a valid one (count_wraps on it and the run)
            carried = continues and has_last[b, c]
            n = count[b, c] if carried else 0
            last = last_phase[b, c]
            have = carried and math.isfinite(last)
            t_last = -1
            for t in range(n_time):
                if t > 0 and scan_of_time[t] != scan_of_time[t - 1]:
                    n, have = 0, False
                ph = phase[b, c, t]
                if valid[b, c, t] and math.isfinite(ph):
                    if have:
                        n = wrap_step(n, last, ph)
                    last, have = ph, True
                    if t >= last_start:
                        t_last = t
                wraps[b, c, t] = n
            if t_last >= 0:
                new_phase[b, c] = phase[b, c, t_last]
                new_has[b, c] = True
                new_count[b, c] = wraps[b, c, t_last]
            elif not (last_start == 0 and continues):
                new_has[b, c] = False
                new_count[b, c] = 0
    return wraps, new_phase, new_has, new_count


@numba.njit(cache=True, nogil=True)
def wrap_events(wraps, scan_of_time):
    """Number of wraps counted in each series of ``wraps`` (..., n_time): sum of |steps|.

    Steps between two scans are not wraps: the count restarts at 0 in every
    scan, and that reset must not be reported as wrap events.
    """
    flat = wraps.reshape(-1, wraps.shape[-1])
    events = np.zeros(flat.shape[0], dtype=np.int64)
    for s in range(flat.shape[0]):
        for t in range(1, flat.shape[1]):
            if scan_of_time[t] == scan_of_time[t - 1]:
                events[s] += abs(flat[s, t] - flat[s, t - 1])
    return events.reshape(wraps.shape[:-1])


@dataclass
class Carry:
    """State of each (baseline, correlation) series at the end of the previous chunk."""

    last_phase: np.ndarray   # (n_bl, n_corr) float64 last valid phase
    has_last: np.ndarray     # (n_bl, n_corr) bool
    count: np.ndarray        # (n_bl, n_corr) int64 wrap count at that sample
    last_scan: int = -1      # scan index of the previous chunk's last time

    @classmethod
    def empty(cls, n_bl: int, n_corr: int) -> "Carry":
        return cls(np.zeros((n_bl, n_corr)), np.zeros((n_bl, n_corr), bool),
                   np.zeros((n_bl, n_corr), np.int64), -1)

    def subset(self, bls) -> "Carry":
        """The carry of the baselines ``bls`` (a baseline batch's task gets only its own)."""
        return Carry(self.last_phase[bls], self.has_last[bls], self.count[bls], self.last_scan)


def count_scans(phase: np.ndarray, valid: np.ndarray, scan_of_time: np.ndarray, carry: Carry):
    """Wrap counts (n_bl, n_corr, n_time) of every series, and the carry after them.

    :func:`count_wraps`'s rule on each scan run of each series (:func:`count_chunk`, one
    kernel call for the whole chunk); a run that continues the previous chunk's scan is
    prefixed with the carried last valid sample, so the count goes on where it stopped.
    ``carry`` is not changed: the carry after this chunk is returned.  Phases are compared
    in float64 (the phases of :func:`hitops.kernels.fpt.gather_phase` are).
    """
    wraps, last_phase, has_last, count = count_chunk(
        np.asarray(phase, dtype=np.float64), valid, scan_of_time, carry.last_phase,
        carry.has_last, carry.count, carry.last_scan)
    last_scan = int(scan_of_time[-1]) if scan_of_time.size else carry.last_scan
    return wraps, Carry(last_phase, has_last, count, last_scan)


def chunk_wrap_events(wraps: np.ndarray, scan_of_time: np.ndarray, carry: Carry) -> np.ndarray:
    """Wrap events (n_bl, n_corr) of one chunk's counts; ``carry``: the one before the chunk.

    The first sample's step from the carried count counts too when it
    continues the previous chunk's scan, so the sum over chunks does not
    depend on the chunk size.
    """
    steps = wrap_events(np.ascontiguousarray(wraps), scan_of_time)
    if wraps.shape[-1] and scan_of_time[0] == carry.last_scan and carry.has_last.any():
        first = wraps[:, :, 0] - np.where(carry.has_last, carry.count, 0)
        steps = steps + np.abs(np.where(carry.has_last, first, 0))
    return steps


@dataclass
class CountedWraps(BatchWraps):
    """A baseline batch's wraps, counted inside its transfer task from the carried sample."""

    carry: Carry

    def resolve(self, ref_phase, ref_valid, scan_of_time) -> ResolvedWraps:
        wraps, after = count_scans(ref_phase, ref_valid, scan_of_time, self.carry)
        return ResolvedWraps(ref_phase, ref_valid, wraps,
                             chunk_wrap_events(wraps, scan_of_time, self.carry), after)


@dataclass
class CountedChunk(ChunkTracking):
    """A chunk the count tracker leaves to the tasks: each gets its baselines' carry."""

    carry: Carry

    def for_batch(self, bls) -> CountedWraps:
        return CountedWraps(self.carry.subset(bls))


class CountTracker(WrapTracker):
    """``--tracker count`` over the whole (n_bl, n_corr, n) grid, chunk after chunk.

    ``track`` takes the gridded visibilities (complex; their phase is used) or
    already wrapped phases (float: used as they are, e.g. the phases
    :func:`hitops.kernels.fpt.gather_phase` gives).  It reads no context
    (``context`` 0): its state is the :class:`Carry`.  ``sigma`` is not used.
    """

    name = "count"
    grids_reference = False
    segmented = False

    def __init__(self, grid: TrackGrid, corr_names, setup=None, **_unused):
        self.grid = grid
        self.setup = setup
        self.context = 0
        self.corr_names = list(corr_names)
        n_bl, n_corr = grid.n_bl, len(self.corr_names)
        self.state = Carry.empty(n_bl, n_corr)
        self.stats = Stats(n_bl, n_corr, 0)
        self.antenna_phase = self.antenna_segment = None   # no antenna model

    def extended(self, t0: int, t1: int):
        return t0, t1

    def track(self, t_lo, t0, t1, t_hi, vis, valid, sigma=None) -> Tracked:
        i0, i1 = t0 - t_lo, t1 - t_lo
        vis, valid = vis[..., i0:i1], valid[..., i0:i1]
        phase = np.angle(vis) if np.iscomplexobj(vis) else np.asarray(vis, dtype=np.float64)
        scan = self.grid.scans.scan_of_time[t0:t1]
        wraps, carry = count_scans(phase, valid, scan, self.state)
        self.stats.per_series["wrap_events"] += chunk_wrap_events(wraps, scan, self.state)
        self.state = carry
        return Tracked(ref_wraps=wraps)

    def track_chunk(self, t0, t1, reference=None) -> CountedChunk:
        """The counting is left to the transfer tasks (:class:`CountedWraps`)."""
        return CountedChunk(self.state)

    def absorb(self, bls, carry: Carry, wrap_events) -> None:
        """The carry after a task of baselines ``bls``, and its wrap events."""
        self.state.last_phase[bls] = carry.last_phase
        self.state.has_last[bls] = carry.has_last
        self.state.count[bls] = carry.count
        self.stats.per_series["wrap_events"][bls] += wrap_events

    def finish_chunk(self, t1: int) -> None:
        self.state.last_scan = int(self.grid.scans.scan_of_time[t1 - 1])

    def report(self, times) -> dict:
        """The JSON report's tracking entry: wrap events per baseline."""
        events = self.stats.per_series["wrap_events"]
        return {"setup": {"tracker": "count"},
                "baselines": [{"baseline": name, "wrap_events": int(events[b].sum())}
                              for b, name in enumerate(self.grid.baseline_names)]}
