"""What the antenna tracker carries from one chunk to the next, per (correlation, antenna).

The antenna tracker's wrap ambiguity lives in the antennas, so its history
is per antenna: the aligned unwrapped antenna phases, counts and segments of
the last ``context`` samples, and the last valid sample's scan, count and
segment.  A new chunk's antenna solve may sit in a frame rotated by a common
angle (another reference antenna): that angle is removed before the counts
are compared (:meth:`AntennaHistory.align`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .state import Overlap, Stats, flag_series, keep_last

TWO_PI = 2.0 * math.pi


@dataclass
class AntennaHistory:
    """Per (correlation, antenna): the aligned last ``context`` samples and the last valid one."""

    context: int
    t_start: int
    unw: np.ndarray              # (n_corr, n_ant, <= context) float64 unwrapped antenna phases
    counts: np.ndarray           # int64
    seg: np.ndarray              # int64
    valid: np.ndarray            # bool
    last_scan: np.ndarray        # (n_corr, n_ant)
    last_count: np.ndarray
    last_seg: np.ndarray
    flag_seg: np.ndarray         # (n_corr, n_ant, 2)

    @classmethod
    def empty(cls, context: int, n_corr: int, n_ant: int) -> "AntennaHistory":
        shape = (n_corr, n_ant)
        return cls(context, 0, np.zeros(shape + (0,)), np.zeros(shape + (0,), np.int64),
                   np.zeros(shape + (0,), np.int64), np.zeros(shape + (0,), bool),
                   np.full(shape, -1, np.int64), np.zeros(shape, np.int64),
                   np.full(shape, -1, np.int64), np.full(shape + (2,), -1, np.int64))

    def _offsets(self, c, out, ov: Overlap, a):
        """Count and segment offsets (n_ant,) that put one run's antennas onto the history."""
        n_ant = out["ant_counts"].shape[0]
        sl = slice(ov.run_a - a, ov.i0 - a)
        new_unw = out["ant_phase"] - TWO_PI * out["ant_counts"]
        offs = np.zeros(n_ant, np.int64)
        soffs = np.zeros(n_ant, np.int64)
        diffs = {}
        for p in range(n_ant):
            both = out["ant_valid"][p, sl] & self.valid[c, p, ov.hcol]
            if both.any():
                j = np.flatnonzero(both)[-1]
                diffs[p] = (new_unw[p, sl][j] - self.unw[c, p, ov.hcol[j]],
                            self.seg[c, p, ov.hcol[j]] - out["ant_seg"][p, sl][j])
        if diffs:
            # common frame rotation between the two solves (same for all antennas)
            frame = math.atan2(sum(math.sin(d) for d, _ in diffs.values()),
                               sum(math.cos(d) for d, _ in diffs.values()))
            for p, (d, s) in diffs.items():
                offs[p] = int(round((d - frame) / TWO_PI))
                soffs[p] = s
        for p in range(n_ant):
            if p not in diffs and self.last_scan[c, p] == ov.scan:
                # a gap longer than the context: a new segment that continues the count
                later = np.flatnonzero(out["ant_valid"][p, ov.i0 - a:])
                if later.size:
                    k = ov.i0 - a + later[0]
                    offs[p] = self.last_count[c, p] - out["ant_counts"][p, k]
                    soffs[p] = self.last_seg[c, p] + 1 - out["ant_seg"][p, k]
        return offs, soffs

    def align(self, ov: Overlap, ant: dict, relink) -> None:
        """Shift the antenna counts and segments of the run at the chunk start onto the
        history; ``relink(c, a, b, out)`` then redoes that run's baseline counts."""
        if ov is None:
            return
        for c, runs in ant.items():
            for a, b, out in runs:
                if not (a <= ov.i0 < b):
                    continue
                offs, soffs = self._offsets(c, out, ov, a)
                out["ant_counts"] = out["ant_counts"] + offs[:, None]
                out["ant_seg"] = np.where(out["ant_seg"] >= 0, out["ant_seg"] + soffs[:, None], -1)
                relink(c, a, b, out)

    def jump_flags(self, ant, i0, i1, scan, valid, ant1, ant2, exclude) -> None:
        """--jump-action flag: a baseline sample is excluded when either antenna is flagged."""
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                bad = np.zeros((self.unw.shape[1], hi - lo), bool)
                for p in range(bad.shape[0]):
                    k = slice(lo - a, hi - a)
                    bad[p], self.flag_seg[c, p] = flag_series(
                        out["ant_valid"][p, k], out["ant_jump"][p, k], scan[lo:hi],
                        out["ant_seg"][p, k], self.flag_seg[c, p])
                exclude[:, c, lo:hi] = (bad[ant1] | bad[ant2]) & valid[:, c, lo:hi]

    def _collect_antenna(self, stats: Stats, c, p, out, k, scan, t_index) -> None:
        """Confidence numbers of antenna p's valid samples ``k`` of one run."""
        sa = stats.per_antenna
        sc = scan[k]
        prev_scan = np.concatenate([[self.last_scan[c, p]], sc[:-1]])
        prev_seg = np.concatenate([[self.last_seg[c, p]], out["ant_seg"][p, k[:-1]]])
        prev_count = np.concatenate([[self.last_count[c, p]], out["ant_counts"][p, k[:-1]]])
        same = sc == prev_scan
        sus = out["ant_suspect"][p, k]
        prev_sus = np.concatenate([[False], sus[:-1]])
        sa["suspect_samples"][c, p] += int(sus.sum())
        sa["suspected_slips"][c, p] += int((sus & ~prev_sus).sum())
        sa["bridged_gaps"][c, p] += int(out["ant_bridged"][p, k].sum())
        starts = ~same | (out["ant_seg"][p, k] != prev_seg)
        sa["segments"][c, p] += int(starts.sum())
        is_jump = out["ant_jump"][p, k] != 0
        sa["long_gap_segments"][c, p] += int((starts & same & ~is_jump).sum())
        sa["jumps"][c, p] += int(is_jump.sum())
        for kk in k[is_jump]:
            stats.ant_jumps.append((c, p, t_index + int(kk), float(out["ant_jump"][p, kk])))
        sa["wrap_events"][c, p] += int(np.abs(out["ant_counts"][p, k] - prev_count)[same].sum())
        self.last_scan[c, p] = sc[-1]
        self.last_count[c, p] = out["ant_counts"][p, k[-1]]
        self.last_seg[c, p] = out["ant_seg"][p, k[-1]]

    def collect(self, stats: Stats, ant, t_lo, i0, i1, scan) -> None:
        """Per-antenna confidence numbers of the samples [i0, i1)."""
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                for p in range(out["ant_valid"].shape[0]):
                    k = np.flatnonzero(out["ant_valid"][p, lo - a:hi - a]) + lo - a
                    if k.size:
                        self._collect_antenna(stats, c, p, out, k, scan[a:], t_lo + a)

    def remember(self, ant, t0, t1, i0, i1) -> None:
        """Keep the aligned antenna results of the last ``context`` samples up to t1."""
        n_corr, n_ant = self.last_scan.shape
        shape = (n_corr, n_ant, i1 - i0)
        unw, counts = np.zeros(shape), np.zeros(shape, np.int64)
        seg, valid = np.full(shape, -1, np.int64), np.zeros(shape, bool)
        for c, runs in ant.items():
            for a, b, out in runs:
                lo, hi = max(a, i0), min(b, i1)
                if lo >= hi:
                    continue
                src, dst = slice(lo - a, hi - a), slice(lo - i0, hi - i0)
                unw[c, :, dst] = out["ant_phase"][:, src] - TWO_PI * out["ant_counts"][:, src]
                counts[c, :, dst] = out["ant_counts"][:, src]
                seg[c, :, dst] = out["ant_seg"][:, src]
                valid[c, :, dst] = out["ant_valid"][:, src]
        if self.t_start + self.unw.shape[-1] != t0:     # not contiguous: start afresh
            self.unw, self.counts, self.seg, self.valid = (
                x[..., :0] for x in (self.unw, self.counts, self.seg, self.valid))
            self.t_start = t0
        drop = max(0, self.unw.shape[-1] + (t1 - t0) - self.context)
        self.unw = keep_last(self.unw, unw, drop)
        self.counts = keep_last(self.counts, counts, drop)
        self.seg = keep_last(self.seg, seg, drop)
        self.valid = keep_last(self.valid, valid, drop)
        self.t_start += drop
