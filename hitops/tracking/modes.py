"""Tracking modes over a (baseline, time) grid, whole tracks at once (tests, benchmarks).

Modes:

* ``naive``   - :func:`hitops.tracking.count.count_wraps` per baseline (the paper's PWC);
* ``smooth``  - :func:`hitops.tracking.smooth_kernel.track_wraps_smooth` per baseline
  (smoothed unit phasor, gap bridging, jump detection);
* ``antenna`` - solve antenna phases at the reference band, track each
  antenna with ``antenna_tracker`` (``naive`` or ``smooth``), transfer the
  counts to baselines (:mod:`hitops.tracking.antenna_kernel`).

Every function returns a :class:`TrackResult` whose arrays are (n_bl, n_time)
and whose ``summary()`` gives the per-baseline (and per-antenna) confidence
numbers for logs and ``hitops diagnose``: suspected slips, bridged gaps,
segments, jumps with their times.

The kernels work in samples of a *regular* time grid;
:func:`hitops.tracking.grid.grid_positions` maps the distinct times of a layout
onto one (missing times become invalid samples, so a scan gap is a gap the
tracker can see).  These are the offline forms (tests, benchmarks, diagnose);
calibrate runs the trackers of :mod:`hitops.tracking.smooth` and
:mod:`hitops.tracking.antenna` chunk by chunk.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .antenna_kernel import baseline_counts_from_antennas, solve_antenna_phases
from .count import count_wraps
from .smooth_kernel import track_wraps_smooth
from .windows import running_sum

MODES = ("naive", "smooth", "antenna")
SMOOTH_PARAMS = ("half_window", "max_gap", "jump_window", "jump_threshold", "min_coherence",
                 "half_windows")


@dataclass
class TrackResult:
    counts: np.ndarray                 # int64 (n_series, n_time)
    segment: np.ndarray                # int64 (n_series, n_time), -1 where invalid
    suspect: np.ndarray                # bool
    bridged: np.ndarray                # bool, first sample after a bridged gap
    jump: np.ndarray                   # float64, measured jump (rad) or 0
    extra: dict = field(default_factory=dict)

    def summary(self, times=None, names=None) -> list[dict]:
        """One row per series: suspected slips, bridged gaps, segments, jumps (times)."""
        rows = []
        for s in range(self.counts.shape[0]):
            jump_idx = np.flatnonzero(self.jump[s])
            rows.append({
                "name": names[s] if names is not None else s,
                "suspected_slips": int(self.suspect[s].sum()),
                "bridged_gaps": int(self.bridged[s].sum()),
                "segments": int(self.segment[s].max() + 1) if self.segment[s].size else 0,
                "jumps": int(jump_idx.size),
                "jump_times": [float(times[i]) if times is not None else int(i) for i in jump_idx],
                "jump_sizes_deg": [float(np.degrees(self.jump[s, i])) for i in jump_idx],
            })
        return rows


def _smooth_kwargs(params: dict) -> dict:
    unknown = set(params) - set(SMOOTH_PARAMS)
    if unknown:
        raise InputError(f"unknown tracking parameters {sorted(unknown)}; known: {', '.join(SMOOTH_PARAMS)}")
    return params


def track_series(ref_phase: np.ndarray, valid: np.ndarray, mode: str = "smooth", **params) -> TrackResult:
    """Track each row of ``ref_phase`` (n_series, n_time) with ``naive`` or ``smooth``."""
    ref_phase = np.ascontiguousarray(ref_phase, dtype=np.float64)
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    if ref_phase.ndim != 2 or ref_phase.shape != valid.shape:
        raise InputError(f"ref_phase and valid must both be (n_series, n_time); got "
                         f"{ref_phase.shape} and {valid.shape}")
    n_series, n_time = ref_phase.shape
    counts = np.zeros((n_series, n_time), np.int64)
    segment = np.full((n_series, n_time), -1, np.int64)
    suspect = np.zeros((n_series, n_time), bool)
    bridged = np.zeros((n_series, n_time), bool)
    jump = np.zeros((n_series, n_time))
    if mode == "naive":
        if params:
            raise InputError(f"the naive tracker takes no parameters (got {sorted(params)})")
        for s in range(n_series):
            counts[s] = count_wraps(ref_phase[s], valid[s])
            segment[s][valid[s] & np.isfinite(ref_phase[s])] = 0
    elif mode == "smooth":
        kwargs = _smooth_kwargs(params)
        per_sample = kwargs.pop("half_windows", None)
        if per_sample is not None:
            per_sample = np.ascontiguousarray(np.broadcast_to(per_sample, ref_phase.shape), dtype=np.int64)
        for s in range(n_series):
            extra = {} if per_sample is None else {"half_windows": per_sample[s]}
            counts[s], segment[s], suspect[s], bridged[s], jump[s] = \
                track_wraps_smooth(ref_phase[s], valid[s], **kwargs, **extra)
    else:
        raise InputError(f"unknown tracking mode '{mode}' for single series; use naive or smooth")
    return TrackResult(counts, segment, suspect, bridged, jump)


def track_antennas(ref_vis: np.ndarray, valid: np.ndarray, ant1, ant2, n_ant: int,
                   refants=(), antenna_tracker: str = "smooth", solve_half_window: int = 0,
                   **params) -> TrackResult:
    """Antenna-based wrap counts for every baseline of a (n_bl, n_time) reference grid.

    ``ref_vis`` complex64 or complex128 visibilities at the reference band.
    ``solve_half_window`` > 0 solves the antenna phases from visibilities
    summed over +-that many samples (shorter than the coherence time; an int
    array (n_time,) gives each time its own half-window): the
    solve then has the SNR of the window, while each baseline sample is still
    snapped individually to the antenna model.
    The result's arrays are per baseline; ``extra`` holds the per-antenna
    phases, counts and diagnostics (``antenna``: a TrackResult over antennas),
    the reference antenna used at each sample and the frame breaks.
    """
    ref_vis = np.ascontiguousarray(ref_vis)
    if not np.iscomplexobj(ref_vis):
        raise InputError("antenna-based tracking needs complex reference visibilities, "
                         f"got dtype {ref_vis.dtype}")
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    ant1 = np.asarray(ant1, dtype=np.int64)
    ant2 = np.asarray(ant2, dtype=np.int64)
    if ant1.size != ref_vis.shape[0] or ant2.size != ref_vis.shape[0]:
        raise InputError(f"ant1/ant2 ({ant1.size}, {ant2.size}) must match the {ref_vis.shape[0]} baselines")
    if n_ant <= max(ant1.max(initial=-1), ant2.max(initial=-1)):
        raise InputError(f"n_ant={n_ant} is smaller than the largest antenna index in ant1/ant2")
    refants = np.asarray(list(refants), dtype=np.int64)
    windowed = np.any(np.asarray(solve_half_window) > 0)
    # the sum of the valid visibilities within +-solve_half_window samples
    summed = np.where(valid & np.isfinite(ref_vis), ref_vis, 0).astype(np.complex128)
    solve_vis = running_sum(summed, solve_half_window) if windowed else ref_vis
    ant_phase, ant_valid, ref_used, frame_break = solve_antenna_phases(solve_vis, valid, ant1, ant2,
                                                                       n_ant, refants)
    # a frame break makes every antenna phase jump arbitrarily: track the pieces separately
    cuts = [0] + list(np.flatnonzero(frame_break)) + [ref_vis.shape[1]]
    pieces = []
    for start, stop in zip(cuts[:-1], cuts[1:]):
        piece = track_series(ant_phase[:, start:stop], ant_valid[:, start:stop], antenna_tracker, **params)
        pieces.append(piece)
    ant_result = _concatenate(pieces)
    counts, unmodelled = baseline_counts_from_antennas(np.angle(ref_vis.astype(np.complex128)), valid,
                                                       ant1, ant2, ant_phase, ant_valid, ant_result.counts)
    # a baseline inherits its antennas' diagnostics
    suspect = (ant_result.suspect[ant1] | ant_result.suspect[ant2]) & valid
    bridged = (ant_result.bridged[ant1] | ant_result.bridged[ant2]) & valid
    jump = np.where(ant_result.jump[ant1] != 0, ant_result.jump[ant1], -ant_result.jump[ant2]) * valid
    segment = np.where(valid, ant_result.segment[ant1].clip(0) + ant_result.segment[ant2].clip(0), -1)
    return TrackResult(counts, segment, suspect | unmodelled, bridged, jump,
                       extra={"antenna": ant_result, "ant_phase": ant_phase, "ant_valid": ant_valid,
                              "ref_used": ref_used, "frame_break": frame_break,
                              "unmodelled": unmodelled})


def _concatenate(pieces: list[TrackResult]) -> TrackResult:
    """Join time pieces; segment ids continue, counts restart per piece (offsets unresolved)."""
    if len(pieces) == 1:
        return pieces[0]
    seg_parts = []
    offset = np.zeros(pieces[0].segment.shape[0], np.int64)
    for piece in pieces:
        seg = np.where(piece.segment >= 0, piece.segment + offset[:, None], -1)
        seg_parts.append(seg)
        offset = np.maximum(offset, seg.max(axis=1, initial=-1) + 1)
    return TrackResult(np.concatenate([p.counts for p in pieces], axis=1),
                       np.concatenate(seg_parts, axis=1),
                       np.concatenate([p.suspect for p in pieces], axis=1),
                       np.concatenate([p.bridged for p in pieces], axis=1),
                       np.concatenate([p.jump for p in pieces], axis=1))


def track_series_dask(ref_phase, valid, mode: str = "smooth", **params) -> dict:
    """Dask version of :func:`track_series`: one task per baseline chunk.

    ``ref_phase`` and ``valid`` are dask arrays (n_bl, n_time) chunked along
    baselines only (a tracker needs the whole time axis).  Returns a dict of
    dask arrays with the fields of :class:`TrackResult`; nothing is computed.
    """
    import dask
    import dask.array as da

    if len(ref_phase.chunks[1]) != 1:
        raise InputError("track_series_dask needs the time axis in one chunk "
                         f"(got {len(ref_phase.chunks[1])} time chunks); rechunk with {{1: -1}}")
    valid = valid.rechunk(ref_phase.chunks)
    fields = {"counts": np.int64, "segment": np.int64, "suspect": np.bool_, "bridged": np.bool_,
              "jump": np.float64}
    blocks = {name: [] for name in fields}
    n_time = ref_phase.shape[1]
    for phase_block, valid_block, n_rows in zip(ref_phase.to_delayed()[:, 0], valid.to_delayed()[:, 0],
                                                ref_phase.chunks[0]):
        result = dask.delayed(track_series, nout=None, pure=True)(phase_block, valid_block, mode, **params)
        for name, dtype in fields.items():
            part = dask.delayed(getattr, pure=True)(result, name)
            blocks[name].append(da.from_delayed(part, (n_rows, n_time), dtype=dtype))
    return {name: da.concatenate(parts, axis=0) for name, parts in blocks.items()}
