"""``--tracker antenna``: wraps tracked per antenna, baseline counts from the antenna model.

Per parallel-hand correlation and scan run: a per-sample antenna phase solve
(optionally over a window of summed visibilities, sized from the antennas'
combined SNR), the smooth tracker on each antenna's phase, and each
baseline's count snapped to the antenna model A_p - A_q
(:func:`hitops.tracking.modes.track_antennas`), so n0 is per antenna and
closure phases carry no 2 pi eps k.  The baseline's reference phase becomes
its antenna model (``Tracked.ref_model``): R times it is what the target band
receives, so the target's closure phases are kept (docs/tracking.md).
Cross-hand correlations (RL, LR, XY, YX) have no antenna model here and are
tracked per baseline as by :class:`hitops.tracking.smooth.SmoothTracker`,
which this tracker extends; the antennas' history across chunks is
:class:`hitops.tracking.antenna_state.AntennaHistory`.
"""

from __future__ import annotations

import logging
from typing import Dict

import numpy as np

from .antenna_kernel import baseline_counts_from_antennas, solve_antenna_phases
from .antenna_state import AntennaHistory
from .grid import TrackGrid, on_grid
from .modes import track_antennas
from .options import ANTENNA_TRACK_HALF_WINDOW, MIN_COHERENCE
from .smooth import Chunk, Run, SmoothTracker
from .state import PAIR_KEY, Stats, jump_list
from .windows import half_windows, per_sample_snr

log = logging.getLogger("hitops.calibrate")

TWO_PI = 2.0 * np.pi


def _wrap_pi(x):
    """Radians wrapped to [-pi, pi) (NaN stays NaN)."""
    return (x + np.pi) % TWO_PI - np.pi


def per_sample_model(out):
    """Unwrapped per-sample antenna phases on the tracked antennas' lobes; (phase, valid).

    ``out``: one scan run of :meth:`AntennaTracker._antenna`, aligned.  The
    per-sample solution and the tracked one may sit in frames rotated by a common
    angle (reference-antenna changes): that angle (circular mean over the antennas)
    is removed before each antenna takes the 2 pi lobe nearest its tracked phase.
    A common angle cancels in every baseline A_p - A_q.
    """
    tracked = out["ant_phase"] - TWO_PI * out["ant_counts"]
    ok = out["raw_valid"] & out["ant_valid"] & np.isfinite(out["raw_phase"])
    raw = np.where(ok, out["raw_phase"], 0.0)
    frame = np.angle(np.sum(np.where(ok, np.exp(1j * (tracked - raw)), 0), axis=0))
    raw = raw + frame[None, :]
    model = raw + TWO_PI * np.round((np.where(ok, tracked, 0.0) - raw) / TWO_PI)
    return model, ok


class AntennaTracker(SmoothTracker):
    """Runs the antenna tracker chunk by chunk (see the module doc)."""

    name = "antenna"
    records = (("antenna_phase", np.nan), ("antenna_segment", -1))

    def __init__(self, grid: TrackGrid, corr_names, setup, n_ant: int = 0, antenna_names=(),
                 workers: int = 0, sin_elevation=None):
        super().__init__(grid, corr_names, setup, n_ant, antenna_names, workers, sin_elevation)
        parallel = [len(c) == 2 and c[0] == c[1] for c in self.corr_names]
        self.antenna_corrs = [c for c in range(self.n_corr) if parallel[c]]
        self.smooth_corrs = [c for c in range(self.n_corr) if not parallel[c]]
        self.antennas = AntennaHistory.empty(setup.context, self.n_corr, n_ant)
        # each station's unwrapped reference phase per correlation and union time, as
        # transferred (the gains of a calibration table); NaN where unsolved ...
        self.antenna_phase = np.full((n_ant, self.n_corr, grid.n_time), np.nan)
        # ... and its tracking segment (aligned across chunks; -1 where none)
        self.antenna_segment = np.full((n_ant, self.n_corr, grid.n_time), -1, np.int64)
        if not self.antenna_corrs:
            log.warning("antenna tracking needs parallel-hand correlations (RR, LL, XX, YY); "
                        "%s are tracked per baseline with the smooth tracker",
                        ",".join(self.corr_names))

    # -- the parallel hands of one scan run
    def _antenna_run(self, run: Run, t_lo, sigma, ch: Chunk) -> None:
        # one correlation per thread: each returns what it found, nothing shared is changed
        solved = self._each(lambda c: self._antenna_corr(run, t_lo, sigma, c),
                            self.antenna_corrs)
        for c, out in zip(self.antenna_corrs, solved):
            self.stats.frame_breaks += out.pop("frame_breaks")
            span = slice(run.a, run.b)
            ch.counts[:, c, span], ch.seg[:, c, span] = out["counts"], out["seg"]
            ch.suspect[:, c, span], ch.bridged[:, c, span] = out["suspect"], out["bridged"]
            ch.unmodelled[:, c, span] = out["unmodelled"]
            ch.ant.setdefault(c, []).append((run.a, run.b, out))

    def _antenna_corr(self, run: Run, t_lo, sigma, c: int) -> Dict:
        """Antenna mode on correlation ``c`` of one scan run (:meth:`_antenna`'s results)."""
        solve_h = self.setup.solve_half_window
        if solve_h < 0:
            tc_t = None
            if self.station_tc is not None:
                # the antennas present: the lowest one's local t_c sets the window
                tc_t = on_grid(self.station_tc[:, t_lo + run.a:t_lo + run.b].min(axis=0),
                               run.pos, run.length)
            reg_sigma = (None if sigma is None
                         else on_grid(sigma[:, c, run.a:run.b], run.pos, run.length))
            solve_h = self._solve_windows(run.vis[:, c], run.valid[:, c], reg_sigma, tc_t)
        return self._antenna(run.vis[:, c], run.valid[:, c], run.pos, solve_h)

    def _solve_windows(self, vis, valid, sigma, coherence_time=None):
        """Per-time solve half-windows from the antennas' combined per-sample SNR.

        An antenna solution combines its baselines: its SNR is about
        sqrt(sum of rho_pq^2) over its baselines (stations.antenna_snr); each
        baseline feeds two antennas, so the typical antenna has
        sqrt(2 sum_b rho_b^2 / n_present).
        """
        setup = self.setup
        rho = per_sample_snr(vis, valid, sigma, setup.snr_window)
        power = np.nansum(np.where(valid, rho, 0.0) ** 2, axis=0)
        present = np.zeros((self.n_ant, valid.shape[1]), bool)
        present[self.grid.ant1] |= valid
        present[self.grid.ant2] |= valid
        n_present = present.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            rho_ant = np.sqrt(2.0 * power / n_present)
        return half_windows(np.where(n_present > 0, rho_ant, np.nan),
                            setup.coherence_time if coherence_time is None else coherence_time,
                            setup.dt, widest=setup.max_half_window)

    def _antenna(self, vis, valid, pos, solve_half_window):
        """Antenna mode on one regular scan run of one correlation; results at ``pos``."""
        setup = self.setup
        fixed = np.ndim(solve_half_window) == 0
        res = track_antennas(vis, valid, self.grid.ant1, self.grid.ant2, self.n_ant,
                             refants=setup.refants, antenna_tracker="smooth",
                             solve_half_window=solve_half_window,
                             half_window=ANTENNA_TRACK_HALF_WINDOW, max_gap=setup.max_gap,
                             # a windowed solve spreads a jump over 2 s + 1 samples: the
                             # jump statistic must compare windows at least that long
                             jump_window=(max(setup.jump_window, 2 * int(solve_half_window) + 1)
                                          if fixed else setup.jump_window),
                             jump_threshold=setup.jump_threshold, min_coherence=MIN_COHERENCE)
        ant_res = res.extra["antenna"]
        # the phases transferred in antenna mode are solved per sample: the windowed solve
        # above chooses the lobes, but its smoothing error would enter the target band
        if np.any(np.asarray(solve_half_window) > 0):
            raw_phase, raw_valid = solve_antenna_phases(
                np.ascontiguousarray(vis), np.ascontiguousarray(valid), self.grid.ant1,
                self.grid.ant2, self.n_ant, np.asarray(setup.refants, np.int64))[:2]
        else:
            raw_phase, raw_valid = res.extra["ant_phase"], res.extra["ant_valid"]
        return {"counts": res.counts[:, pos], "seg": res.segment[:, pos],
                "suspect": res.suspect[:, pos], "bridged": res.bridged[:, pos],
                "unmodelled": res.extra["unmodelled"][:, pos],
                "ant_phase": res.extra["ant_phase"][:, pos],
                "ant_valid": res.extra["ant_valid"][:, pos],
                "ant_counts": ant_res.counts[:, pos], "ant_seg": ant_res.segment[:, pos],
                "ant_suspect": ant_res.suspect[:, pos], "ant_bridged": ant_res.bridged[:, pos],
                "ant_jump": ant_res.jump[:, pos], "bl_phase": np.angle(vis[:, pos]),
                "raw_phase": raw_phase[:, pos], "raw_valid": raw_valid[:, pos],
                "bl_valid": valid[:, pos],
                # added to the statistics by the caller (one thread per correlation)
                "frame_breaks": int(res.extra["frame_break"][pos].sum())}

    # -- across chunks
    def _align(self, scan, t_lo, t0, ch: Chunk) -> None:
        ov = self.state.overlap(scan, t_lo, t0)
        self.state.align(ov, self.smooth_corrs, ch.valid, ch.counts, ch.seg)

        def relink(c, a, b, out):
            # the baselines of an aligned run take their counts from the shifted antennas
            bl_counts, _ = baseline_counts_from_antennas(
                np.ascontiguousarray(out["bl_phase"]), np.ascontiguousarray(out["bl_valid"]),
                self.grid.ant1, self.grid.ant2, np.ascontiguousarray(out["ant_phase"]),
                np.ascontiguousarray(out["ant_valid"]), np.ascontiguousarray(out["ant_counts"]))
            out["counts"] = bl_counts
            ch.counts[:, c, a:b] = bl_counts

        self.antennas.align(ov, ch.ant, relink)

    def _model(self, t_lo, t0, t1, ch: Chunk):
        """Each baseline's reference phase as its antenna model, the unwrapped difference of
        its two stations' tracked phases, and the counts and segments that go with it."""
        model = np.full(ch.valid.shape, np.nan)
        p_ant, q_ant = self.grid.ant1, self.grid.ant2
        for c, runs in ch.ant.items():
            for a, b, out in runs:
                # a baseline's segment is the pair of its antennas' (aligned) segments
                sp, sq = out["ant_seg"][p_ant], out["ant_seg"][q_ant]
                ch.seg[:, c, a:b] = np.where(ch.valid[:, c, a:b] & (sp >= 0) & (sq >= 0),
                                             sp * PAIR_KEY + sq, -1)
                ant_model, ant_ok = per_sample_model(out)
                # keep this chunk's own times (its context belongs to the neighbours)
                lo, hi = max(a, t0 - t_lo), min(b, t1 - t_lo)
                if hi > lo:
                    self.antenna_phase[:, c, t_lo + lo:t_lo + hi] = np.where(
                        ant_ok, ant_model, np.nan)[:, lo - a:hi - a]
                    self.antenna_segment[:, c, t_lo + lo:t_lo + hi] = out["ant_seg"][:, lo - a:hi - a]
                both = ant_ok[p_ant] & ant_ok[q_ant]
                bl_model = np.where(both, ant_model[p_ant] - ant_model[q_ant], np.nan)
                model[:, c, a:b] = bl_model
                # the count that goes with the model's wrapped phase (unwrapped = phase - 2 pi n)
                with np.errstate(invalid="ignore"):
                    model_counts = np.round((_wrap_pi(bl_model) - bl_model) / TWO_PI)
                ch.counts[:, c, a:b] = np.where(both, model_counts, out["counts"]).astype(np.int64)
        return model

    def _jump_flags(self, scan, i0, i1, ch: Chunk) -> None:
        super()._jump_flags(scan, i0, i1, ch)
        self.antennas.jump_flags(ch.ant, i0, i1, scan, ch.valid, self.grid.ant1,
                                 self.grid.ant2, ch.exclude)

    def _collect(self, scan, t_lo, i0, i1, ch: Chunk) -> None:
        super()._collect(scan, t_lo, i0, i1, ch)
        self.antennas.collect(self.stats, ch.ant, t_lo, i0, i1, scan)

    def _remember(self, t0, t1, i0, i1, ch: Chunk) -> None:
        super()._remember(t0, t1, i0, i1, ch)
        self.antennas.remember(ch.ant, t0, t1, i0, i1)

    def report(self, times: np.ndarray) -> dict:
        """Per-baseline and per-antenna confidence numbers for the JSON report."""
        out = super().report(times)
        st = self.stats
        t_first = float(times[0]) if times.size else 0.0
        antennas = []
        for p, name in enumerate(self.antenna_names):
            if not any(st.per_antenna["segments"][c, p] for c in range(self.n_corr)):
                continue
            entry = {"antenna": name}
            for k in Stats.KEYS:
                if k not in ("unmodelled", "jump_flagged"):
                    entry[k] = int(st.per_antenna[k][:, p].sum())
            entry["jump_list"] = jump_list([(c, t, s) for c, q, t, s in st.ant_jumps if q == p],
                                           times, self.corr_names, t_first)
            antennas.append(entry)
        out["antennas"] = antennas
        out["frame_breaks"] = st.frame_breaks
        return out
