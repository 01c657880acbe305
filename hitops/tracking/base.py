"""The one interface of the three reference-band wrap trackers (count, smooth, antenna).

A calibrate run reads the reference band chunk by chunk.  For chunk [t0, t1)
of the union time axis the pipeline asks the tracker which times it needs
(:meth:`WrapTracker.extended`: ``context`` samples either side for the
smooth and antenna trackers, none for count), reads them, and calls
:meth:`WrapTracker.track_chunk`, which returns a :class:`ChunkTracking` for
[t0, t1).  Each baseline batch's transfer task gets its part of it
(:meth:`ChunkTracking.for_batch`, a :class:`BatchWraps`) and resolves its
reference wraps there (:meth:`BatchWraps.resolve`); the tracker takes back what
the tasks carried (:meth:`WrapTracker.absorb`) and closes the chunk
(:meth:`WrapTracker.finish_chunk`).

Two kinds of tracker sit behind the same calls.  The smooth and antenna
trackers (``grids_reference``) track the whole chunk at once on the reference
band gridded over the chunk and its context (:class:`ReferenceGrid`, their
:meth:`WrapTracker.track`); their tasks only take their slice of the counts
(:class:`TrackedWraps`).  The count tracker needs no context and no grid: it
counts inside each task on the task's own phases, from a carried sample
(:mod:`hitops.tracking.count`), which keeps the driver free for the next
chunk's read.  Chunks must come in time order: that is what makes the counts
independent of the chunk size.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from .state import apply_segment_offsets


@dataclass
class ReferenceGrid:
    """The reference band of [t_lo, t_hi) on the (baseline, correlation, time) grid.

    vis complex128, valid bool, sigma float64 or None: (n_bl, n_corr, t_hi - t_lo),
    baselines in the order of the run's TrackGrid; what a ``grids_reference`` tracker reads.
    """

    t_lo: int
    t_hi: int
    vis: np.ndarray
    valid: np.ndarray
    sigma: Optional[np.ndarray]


@dataclass
class ResolvedWraps:
    """A baseline batch's reference side after its tracker (arrays (n_bl, n_corr, n_time)).

    ref_phase, ref_valid: the phase to transfer and where it is usable; ref_wraps:
    int64 wrap counts; wrap_events (n_bl, n_corr) int64: wraps counted in this task
    (zero when the tracker counts its own); carry: what the task carries to the next
    chunk (:class:`hitops.tracking.count.Carry`), None when the tracker keeps its own
    state in the driver.
    """

    ref_phase: np.ndarray
    ref_valid: np.ndarray
    ref_wraps: np.ndarray
    wrap_events: np.ndarray
    carry: Optional[object] = None


class BatchWraps(ABC):
    """A baseline batch's share of a chunk's tracking, sent with its transfer task."""

    @abstractmethod
    def resolve(self, ref_phase: np.ndarray, ref_valid: np.ndarray,
                scan_of_time: np.ndarray) -> ResolvedWraps:
        """The group's reference wraps, from its gathered reference phase and validity."""


class ChunkTracking(ABC):
    """A chunk's tracking, before it is split over the baseline batches.

    ``segment_keys``: int64 (n_bl, n_corr, t1 - t0) segment key per sample (scan
    index * SEGMENT_KEY + segment, -1 where invalid; the per-segment n0 step), or
    None when the n0 step is per scan.
    """

    segment_keys: Optional[np.ndarray] = None

    @abstractmethod
    def for_batch(self, bls: np.ndarray) -> BatchWraps:
        """The share of the baselines ``bls`` (indices into the chunk's baselines)."""

    def with_segment_offsets(self, segment_k) -> "ChunkTracking":
        """The tracking with the n0 step's integers added per segment (none: itself)."""
        return self


@dataclass
class TrackedWraps(BatchWraps):
    """A baseline batch's slice of a gridded tracker's counts (smooth, antenna)."""

    ref_wraps: np.ndarray
    ref_exclude: Optional[np.ndarray] = None
    ref_model: Optional[np.ndarray] = None

    def resolve(self, ref_phase, ref_valid, scan_of_time) -> ResolvedWraps:
        ref_phase, ref_valid = tracked_reference(ref_phase, ref_valid, self.ref_exclude,
                                                 self.ref_model)
        # the tracker counts its own wrap events across chunks (its stats)
        return ResolvedWraps(ref_phase, ref_valid, self.ref_wraps,
                             np.zeros(self.ref_wraps.shape[:-1], np.int64))


def tracked_reference(ref_phase, ref_valid, exclude, model):
    """The reference phase and validity a robust tracker's output leaves to transfer.

    ``exclude``: reference samples after a jump (--jump-action flag), or None;
    ``model``: antenna mode's unwrapped model phase (NaN where not modelled), or None.
    """
    if exclude is not None:
        ref_valid = ref_valid & ~exclude
    if model is not None and np.isfinite(model).any():
        # antenna mode: the baseline's reference phase is its antenna model (the counts
        # already belong to it), so the transferred phase closes on every triangle;
        # correlations without a model (cross-hands) keep their own phase
        modelled = np.isfinite(model)
        antenna_corr = modelled.any(axis=(0, 2))
        ref_phase = np.where(modelled, (model + np.pi) % (2 * np.pi) - np.pi, ref_phase)
        ref_valid = np.where(antenna_corr[None, :, None], ref_valid & modelled, ref_valid)
    return ref_phase, ref_valid


@dataclass
class Tracked(ChunkTracking):
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

    def for_batch(self, bls) -> TrackedWraps:
        return TrackedWraps(self.ref_wraps[bls],
                            None if self.ref_exclude is None else self.ref_exclude[bls],
                            None if self.ref_model is None else self.ref_model[bls])

    def with_segment_offsets(self, segment_k) -> "Tracked":
        return Tracked(apply_segment_offsets(self.ref_wraps, self.segment_keys, segment_k),
                       self.ref_exclude, self.segment_keys, self.ref_model)


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
    #: ``track_chunk`` needs the reference band gridded over the chunk and its context
    grids_reference: bool = True
    #: its counts come in tracking segments, each with its own n0 (the n0 step per
    #: segment); False: the n0 step is per scan
    segmented: bool = True
    #: attributes made from the plan alone (the grid and what follows from it): a tracker
    #: sent from chunk to chunk between processes leaves them behind (:meth:`packed`)
    plan_parts: Tuple[str, ...] = ("grid",)
    #: whole-track records (n_..., n_time) that each chunk fills for its own times
    #: [t0, t1) only, with their fill values: they travel chunk slice by chunk slice
    records: Tuple[Tuple[str, object], ...] = ()

    @abstractmethod
    def extended(self, t0: int, t1: int):
        """(t_lo, t_hi): the times to read for chunk [t0, t1)."""

    @abstractmethod
    def track(self, t_lo: int, t0: int, t1: int, t_hi: int, vis, valid, sigma) -> Tracked:
        """Counts of chunk [t0, t1) from the reference grid of [t_lo, t_hi).

        vis (complex), valid (bool), sigma (float64 or None):
        (n_bl, n_corr, t_hi - t_lo), baselines in the order of the tracker's ``grid``.
        """

    @abstractmethod
    def report(self, times: np.ndarray) -> dict:
        """The JSON report's ``tracking`` entry after the last chunk."""

    def track_chunk(self, t0: int, t1: int, reference: Optional[ReferenceGrid]) -> ChunkTracking:
        """The tracking of chunk [t0, t1); ``reference``: the gridded reference band of
        :meth:`extended`'s times (None when ``grids_reference`` is False)."""
        return self.track(reference.t_lo, t0, t1, reference.t_hi, reference.vis,
                          reference.valid, reference.sigma)

    def absorb(self, bls: np.ndarray, carry, wrap_events: np.ndarray) -> None:
        """Take back what the task of baselines ``bls`` carried (``ResolvedWraps.carry``)
        and the wrap events it counted (nothing for a tracker whose state stays in the
        driver)."""

    def finish_chunk(self, t1: int) -> None:
        """Chunk [.., t1) is done: every task's share is absorbed."""

    # ---- a tracker carried between processes (hitops/calibrate/worker_chunks.py)
    def packed(self) -> "WrapTracker":
        """A copy of the state alone: no plan parts, no records (what a chunk task hands
        the next one, which may run on another worker)."""
        out = copy.copy(self)
        for name in self.plan_parts + tuple(name for name, _ in self.records):
            setattr(out, name, None)
        return out

    def unpacked(self, plan: "WrapTracker") -> "WrapTracker":
        """This packed tracker on the plan parts and record arrays of ``plan`` (a tracker
        of the same run, made here)."""
        out = copy.copy(self)
        for name in self.plan_parts + tuple(name for name, _ in self.records):
            setattr(out, name, getattr(plan, name))
        return out

    def clear_records(self, t0: int, t1: int) -> None:
        """The records' times [t0, t1) back to their fill values (before a chunk fills them)."""
        for name, fill in self.records:
            getattr(self, name)[..., t0:t1] = fill

    def record_slices(self, t0: int, t1: int) -> Dict[str, np.ndarray]:
        """Copies of the records' times [t0, t1) (what a chunk filled)."""
        return {name: getattr(self, name)[..., t0:t1].copy() for name, _ in self.records}

    def put_records(self, t0: int, t1: int, slices: Dict[str, np.ndarray]) -> None:
        """A chunk's :meth:`record_slices` into this tracker's records."""
        for name, values in slices.items():
            getattr(self, name)[..., t0:t1] = values


def scan_runs(scan_of_time: np.ndarray):
    """(start, stop, scan) of each run of equal scan index (a tracker restarts at each)."""
    if scan_of_time.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(scan_of_time)) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [scan_of_time.size]])
    return [(int(a), int(b), int(scan_of_time[a])) for a, b in zip(starts, stops)]
