"""``--tracker smooth``: the smoothed-phasor tracker per (baseline, correlation) series.

:func:`hitops.tracking.smooth_kernel.track_wraps_smooth` runs on each scan
run of each series of the extended chunk (the chunk with ``context``
reference samples either side), with a smoothing window per sample from the
per-sample SNR and the local coherence time (:mod:`hitops.tracking.windows`),
gap bridging and jump detection.  Its counts are then aligned to the counts
already written for the overlap (:class:`hitops.tracking.state.SeriesHistory`):
the kernels' reach is bounded (smoothing +-h, bridged gaps <= max_gap, jump
windows, the SNR window), so with ``context`` from
:func:`hitops.tracking.options.setup_tracking` the output does not depend on
the chunk size.  Across a gap longer than the context, which is a new,
unresolved segment anyway, the count continues from the last one.

The series run in local threads (the kernel releases the GIL).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Sequence

import numpy as np

from . import theory
from .base import Tracked, WrapTracker, scan_runs
from .grid import TrackGrid, grid_positions, on_grid
from .options import MIN_COHERENCE, TrackingSetup
from .smooth_kernel import track_wraps_smooth
from .state import SeriesHistory, Stats, baseline_report, segment_keys
from .windows import half_windows, per_sample_snr


@dataclass
class Chunk:
    """The arrays of one extended chunk (n_bl, n_corr, n_ext) as the tracker fills them."""

    valid: np.ndarray
    counts: np.ndarray
    seg: np.ndarray
    suspect: np.ndarray
    bridged: np.ndarray
    jump: np.ndarray
    unmodelled: np.ndarray
    exclude: Optional[np.ndarray] = None
    ant: dict = field(default_factory=dict)   # antenna mode: corr -> [(a, b, run results)]

    @classmethod
    def empty(cls, valid: np.ndarray) -> "Chunk":
        shape = valid.shape
        return cls(valid, np.zeros(shape, np.int64), np.full(shape, -1, np.int64),
                   np.zeros(shape, bool), np.zeros(shape, bool), np.zeros(shape),
                   np.zeros(shape, bool))


@dataclass
class Run:
    """One scan run [a, b) of the extended chunk placed on its regular grid of ``length``."""

    a: int
    b: int
    pos: np.ndarray        # grid position of each sample of the run
    length: int
    vis: np.ndarray        # (n_bl, n_corr, length) complex128, 0 where missing
    valid: np.ndarray


def smooth_series(args):
    """track_wraps_smooth on one regular series (a thread-pool job; the kernel is nogil)."""
    phase, valid, hw, setup = args
    kwargs = dict(max_gap=setup.max_gap, jump_window=setup.jump_window,
                  jump_threshold=setup.jump_threshold, min_coherence=MIN_COHERENCE)
    if hw is None:
        return track_wraps_smooth(phase, valid, half_window=setup.half_window, **kwargs)
    # per-sample windows; the scalar half_window sets the base of the gap-bridging rates
    return track_wraps_smooth(phase, valid, half_window=setup.max_half_window, half_windows=hw,
                              **kwargs)


class SmoothTracker(WrapTracker):
    """Runs the smooth tracker chunk by chunk (see the module doc)."""

    name = "smooth"
    plan_parts = ("grid", "pos", "station_tc")

    def __init__(self, grid: TrackGrid, corr_names, setup: TrackingSetup, n_ant: int = 0,
                 antenna_names=(), workers: int = 0, sin_elevation=None):
        self.setup = setup
        self.grid = grid
        self.n_bl = grid.n_bl
        self.n_corr = len(corr_names)
        self.n_ant = n_ant
        self.corr_names = list(corr_names)
        self.antenna_names = list(antenna_names)
        self.context = setup.context
        self.pos, _ = grid_positions(grid.times, grid.scans.scan_of_time)
        # local coherence time per station and time: t_c sin(el)^(3/5) (the phase
        # variance of a thin screen grows with airmass), when the geometry is known
        if sin_elevation is None:
            sin_elevation = setup.sin_elevation
        self.station_tc = None
        if setup.elevation_scaling and sin_elevation is not None:
            self.station_tc = theory.local_coherence_time(setup.coherence_time, sin_elevation)
        self.state = SeriesHistory.empty(setup.context, self.n_bl, self.n_corr)
        self.stats = Stats(self.n_bl, self.n_corr, n_ant)
        self.workers = workers or (os.cpu_count() or 1)
        self.smooth_corrs = list(range(self.n_corr))

    def extended(self, t0: int, t1: int):
        ctx = self.setup.context
        return max(0, t0 - ctx), min(self.grid.n_time, t1 + ctx)

    def track(self, t_lo, t0, t1, t_hi, vis, valid, sigma) -> Tracked:
        """Counts (n_bl, n_corr, t1-t0), excluded samples, segment keys and model of [t0, t1).

        vis/valid/sigma: (n_bl, n_corr, t_hi - t_lo) gridded reference samples.
        """
        scan = self.grid.scans.scan_of_time[t_lo:t_hi]
        ch = Chunk.empty(valid)
        for a, b, _ in scan_runs(scan):
            pos = self.pos[t_lo + a:t_lo + b] - self.pos[t_lo + a]
            length = int(pos[-1]) + 1
            run = Run(a, b, pos, length, on_grid(vis[..., a:b], pos, length, 0j),
                      on_grid(valid[..., a:b], pos, length, False))
            if self.smooth_corrs:
                self._smooth_run(run, t_lo, sigma, ch)
            self._antenna_run(run, t_lo, sigma, ch)
        ch.seg = np.where(valid, ch.seg, -1)
        self._align(scan, t_lo, t0, ch)
        model = self._model(t_lo, t0, t1, ch)
        i0, i1 = t0 - t_lo, t1 - t_lo
        ch.exclude = np.zeros(valid.shape, bool)
        if self.setup.jump_action == "flag":
            self._jump_flags(scan, i0, i1, ch)
        self._collect(scan, t_lo, i0, i1, ch)
        self._remember(t0, t1, i0, i1, ch)
        keys = segment_keys(ch.seg, scan)
        return Tracked(ch.counts[..., i0:i1], ch.exclude[..., i0:i1], keys[..., i0:i1],
                       None if model is None else model[..., i0:i1])

    # -- the smooth series of one scan run
    def _windows(self, run: Run, t_lo, sigma) -> Optional[np.ndarray]:
        """Per-sample half-windows (n_bl, n_corr, length) of the smooth series, or None (fixed)."""
        setup = self.setup
        if setup.half_window != 0:
            return None
        reg_sigma = None if sigma is None else on_grid(sigma[..., run.a:run.b], run.pos, run.length)
        hw = np.ones((self.n_bl, self.n_corr, run.length), np.int64)
        tc_bl = setup.coherence_time
        if self.station_tc is not None:
            # baseline: the worse station's local t_c (docs/tracking.md)
            tc = self.station_tc[:, t_lo + run.a:t_lo + run.b]
            tc_bl = on_grid(np.minimum(tc[self.grid.ant1], tc[self.grid.ant2]), run.pos,
                            run.length)
        def windows_of(c: int) -> np.ndarray:
            rho = per_sample_snr(run.vis[:, c], run.valid[:, c],
                                 None if reg_sigma is None else reg_sigma[:, c], setup.snr_window)
            return half_windows(rho, tc_bl, setup.dt, widest=setup.max_half_window)

        # one correlation per thread: NumPy's loops and sorts let go of the GIL
        for c, windows in zip(self.smooth_corrs, self._each(windows_of, self.smooth_corrs)):
            hw[:, c] = windows
        return hw

    def _each(self, fn: Callable, items: Sequence) -> List:
        """``[fn(item) for item in items]``, on up to ``workers`` threads when there is more
        than one item (the numba kernels and NumPy's loops let go of the GIL)."""
        items = list(items)
        if self.workers > 1 and len(items) > 1:
            with ThreadPoolExecutor(min(self.workers, len(items))) as pool:
                return list(pool.map(fn, items))
        return [fn(item) for item in items]

    def _smooth_run(self, run: Run, t_lo, sigma, ch: Chunk) -> None:
        hw = self._windows(run, t_lo, sigma)
        reg_phase = np.where(run.valid, np.angle(run.vis), np.nan)
        keys = [(bl, c) for bl in range(self.n_bl) for c in self.smooth_corrs]
        jobs = [(np.ascontiguousarray(reg_phase[bl, c]), np.ascontiguousarray(run.valid[bl, c]),
                 None if hw is None else np.ascontiguousarray(hw[bl, c]), self.setup)
                for bl, c in keys]
        results = self._each(smooth_series, jobs)
        span = slice(run.a, run.b)
        for (bl, c), res in zip(keys, results):
            ch.counts[bl, c, span] = res[0][run.pos]
            ch.seg[bl, c, span] = res[1][run.pos]
            ch.suspect[bl, c, span] = res[2][run.pos]
            ch.bridged[bl, c, span] = res[3][run.pos]
            ch.jump[bl, c, span] = res[4][run.pos]

    # -- hooks the antenna tracker fills in (parallel hands)
    def _antenna_run(self, run: Run, t_lo, sigma, ch: Chunk) -> None:
        return None

    def _model(self, t_lo, t0, t1, ch: Chunk) -> Optional[np.ndarray]:
        return None

    # -- across chunks
    def _align(self, scan, t_lo, t0, ch: Chunk) -> None:
        self.state.align(self.state.overlap(scan, t_lo, t0), self.smooth_corrs, ch.valid,
                         ch.counts, ch.seg)

    def _jump_flags(self, scan, i0, i1, ch: Chunk) -> None:
        self.state.jump_flags(self.smooth_corrs, i0, i1, scan, ch.valid, ch.seg, ch.jump,
                              ch.exclude)

    def _collect(self, scan, t_lo, i0, i1, ch: Chunk) -> None:
        self.state.collect(self.stats, t_lo, i0, i1, scan, ch)

    def _remember(self, t0, t1, i0, i1, ch: Chunk) -> None:
        self.state.remember(t0, t1, ch.counts[..., i0:i1], ch.valid[..., i0:i1],
                            ch.seg[..., i0:i1])

    def report(self, times: np.ndarray) -> dict:
        """Per-baseline confidence numbers for the JSON report."""
        return {"setup": self.setup.as_dict(),
                "baselines": baseline_report(self.stats, times, self.grid.baseline_names,
                                             self.corr_names)}
