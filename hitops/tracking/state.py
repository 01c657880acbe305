"""What the smooth and antenna trackers carry from one chunk to the next, and their numbers.

Each chunk is tracked on its extended range (``context`` samples either
side); the counts of the overlap with the previous chunk are already
written, so the new counts are shifted onto them (:meth:`SeriesHistory.align`)
before anything of the chunk is used.  :class:`SeriesHistory` keeps, per
(baseline, correlation) series, the aligned results of the last ``context``
samples and the last valid sample's scan, count and segment; the confidence
numbers of the samples in [t0, t1) go into :class:`Stats`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

#: segment keys are scan index * SEGMENT_KEY + segment id
SEGMENT_KEY = np.int64(1) << 32
#: antenna mode: a baseline's segment id is sp * PAIR_KEY + sq, sp and sq the aligned
#: segment ids of its two antennas (ids of one scan stay far below it)
PAIR_KEY = 1_000_003


@dataclass
class Stats:
    """Confidence numbers per series (baseline x correlation) and per antenna x correlation."""

    n_bl: int
    n_corr: int
    n_ant: int
    per_series: Dict[str, np.ndarray] = field(default_factory=dict)
    per_antenna: Dict[str, np.ndarray] = field(default_factory=dict)
    jumps: List[tuple] = field(default_factory=list)        # (bl, corr, time index, rad)
    ant_jumps: List[tuple] = field(default_factory=list)    # (corr, ant, time index, rad)
    frame_breaks: int = 0

    KEYS = ("suspected_slips", "suspect_samples", "bridged_gaps", "segments",
            "long_gap_segments", "jumps", "jump_flagged", "wrap_events", "unmodelled")

    def __post_init__(self):
        for k in self.KEYS:
            self.per_series[k] = np.zeros((self.n_bl, self.n_corr), np.int64)
            self.per_antenna[k] = np.zeros((self.n_corr, self.n_ant), np.int64)


@dataclass
class Overlap:
    """Where chunk [t0, ...) continues the scan of the previous chunk (extended-chunk indices).

    [run_a, run_b): the scan run holding i0 = t0 - t_lo; ``cols``: the context
    samples [run_a, i0) that the history holds, at history columns ``hcol``.
    """

    i0: int
    run_a: int
    run_b: int
    cols: np.ndarray
    hcol: np.ndarray
    scan: int


def overlap(scan: np.ndarray, t_lo: int, t0: int, t_start: int, n_hist: int) -> Optional[Overlap]:
    """The :class:`Overlap` of a chunk with a history of ``n_hist`` columns from ``t_start``;
    None when the chunk starts a new scan (or nothing came before)."""
    i0 = t0 - t_lo
    if i0 == 0 or n_hist == 0 or i0 >= scan.size or scan[i0] != scan[i0 - 1]:
        return None
    run_a = i0
    while run_a > 0 and scan[run_a - 1] == scan[i0]:
        run_a -= 1
    run_b = i0
    while run_b < scan.size and scan[run_b] == scan[i0]:
        run_b += 1
    hcol = np.arange(run_a, i0) + t_lo - t_start
    okcol = (hcol >= 0) & (hcol < n_hist)
    return Overlap(i0, run_a, run_b, np.arange(run_a, i0)[okcol], hcol[okcol], int(scan[i0]))


def flag_series(ok, jumps, sc, sg, state):
    """Samples of [jump, end of its segment) of one series, continuing ``state`` = (scan,
    segment) flagged by an earlier chunk; returns (flags, state)."""
    out = np.zeros(ok.size, bool)
    starts = np.flatnonzero(ok & (jumps != 0))
    if state[0] < 0 and not starts.size:
        return out, state
    if state[0] >= 0:
        out |= ok & (sc == state[0]) & (sg == state[1])
    for j in starts:
        state = np.array([sc[j], sg[j]])
        out[j:] |= ok[j:] & (sc[j:] == state[0]) & (sg[j:] == state[1])
    return out, state


def keep_last(old: np.ndarray, new: np.ndarray, drop: int) -> np.ndarray:
    """``new`` appended to ``old`` along time, the first ``drop`` columns dropped."""
    return np.concatenate([old, new], axis=-1)[..., drop:]


@dataclass
class SeriesHistory:
    """Per (baseline, correlation): the aligned last ``context`` samples and the last valid one."""

    context: int
    t_start: int                 # time index of column 0 of counts/valid/seg
    counts: np.ndarray           # (n_bl, n_corr, <= context) int64
    valid: np.ndarray            # bool
    seg: np.ndarray              # int64
    last_scan: np.ndarray        # (n_bl, n_corr) scan of the last valid sample (-1: none)
    last_count: np.ndarray
    last_seg: np.ndarray
    last_suspect: np.ndarray
    flag_seg: np.ndarray         # (n_bl, n_corr, 2): (scan, segment) flagged after a jump

    @classmethod
    def empty(cls, context: int, n_bl: int, n_corr: int) -> "SeriesHistory":
        shape = (n_bl, n_corr)
        return cls(context, 0, np.zeros(shape + (0,), np.int64), np.zeros(shape + (0,), bool),
                   np.zeros(shape + (0,), np.int64), np.full(shape, -1, np.int64),
                   np.zeros(shape, np.int64), np.full(shape, -1, np.int64),
                   np.zeros(shape, bool), np.full(shape + (2,), -1, np.int64))

    def overlap(self, scan, t_lo, t0) -> Optional[Overlap]:
        return overlap(scan, t_lo, t0, self.t_start, self.counts.shape[-1])

    def align(self, ov: Overlap, corrs, valid, counts, seg) -> None:
        """Shift the counts and segment ids of the scan run at the chunk start (``corrs``) onto
        the history: by the last sample both saw, else (a gap longer than the context)
        continuing the last count in a new segment."""
        if ov is None:
            return
        for c in corrs:
            for bl in range(counts.shape[0]):
                both = valid[bl, c, ov.cols] & self.valid[bl, c, ov.hcol]
                if both.any():
                    j = np.flatnonzero(both)[-1]
                    off = self.counts[bl, c, ov.hcol[j]] - counts[bl, c, ov.cols[j]]
                    soff = self.seg[bl, c, ov.hcol[j]] - seg[bl, c, ov.cols[j]]
                elif self.last_scan[bl, c] == ov.scan:
                    later = np.flatnonzero(valid[bl, c, ov.i0:ov.run_b])
                    if not later.size:
                        continue
                    k = ov.i0 + later[0]
                    off = self.last_count[bl, c] - counts[bl, c, k]
                    soff = self.last_seg[bl, c] + 1 - seg[bl, c, k]
                else:
                    continue
                run = slice(ov.run_a, ov.run_b)
                counts[bl, c, run] += off
                seg[bl, c, run] = np.where(seg[bl, c, run] >= 0, seg[bl, c, run] + soff, -1)

    def jump_flags(self, corrs, i0, i1, scan, valid, seg, jump, exclude) -> None:
        """--jump-action flag: exclude[..., i0:i1] of ``corrs`` from each jump to its segment's end."""
        sc = scan[i0:i1]
        for bl in range(valid.shape[0]):
            for c in corrs:
                exclude[bl, c, i0:i1], self.flag_seg[bl, c] = flag_series(
                    valid[bl, c, i0:i1], jump[bl, c, i0:i1], sc, seg[bl, c, i0:i1],
                    self.flag_seg[bl, c])

    def collect(self, stats: Stats, t_lo, i0, i1, scan, t) -> None:
        """Confidence numbers of the samples [i0, i1) of every series; ``t``: the chunk's
        arrays (valid, counts, seg, suspect, bridged, jump, unmodelled, exclude)."""
        st = stats.per_series
        for bl in range(t.valid.shape[0]):
            for c in range(t.valid.shape[1]):
                idx = i0 + np.flatnonzero(t.valid[bl, c, i0:i1])
                if not idx.size:
                    continue
                sc = scan[idx]
                prev_scan = np.concatenate([[self.last_scan[bl, c]], sc[:-1]])
                prev_count = np.concatenate([[self.last_count[bl, c]], t.counts[bl, c, idx[:-1]]])
                prev_seg = np.concatenate([[self.last_seg[bl, c]], t.seg[bl, c, idx[:-1]]])
                prev_sus = np.concatenate([[self.last_suspect[bl, c]], t.suspect[bl, c, idx[:-1]]])
                same = sc == prev_scan
                sus = t.suspect[bl, c, idx] | t.unmodelled[bl, c, idx]
                st["suspect_samples"][bl, c] += int(sus.sum())
                st["suspected_slips"][bl, c] += int((sus & ~(prev_sus & same)).sum())
                st["bridged_gaps"][bl, c] += int(t.bridged[bl, c, idx].sum())
                st["unmodelled"][bl, c] += int(t.unmodelled[bl, c, idx].sum())
                starts = ~same | (t.seg[bl, c, idx] != prev_seg)
                st["segments"][bl, c] += int(starts.sum())
                is_jump = t.jump[bl, c, idx] != 0
                st["long_gap_segments"][bl, c] += int((starts & same & ~is_jump).sum())
                st["jumps"][bl, c] += int(is_jump.sum())
                for i in idx[is_jump]:
                    stats.jumps.append((bl, c, t_lo + int(i), float(t.jump[bl, c, i])))
                st["jump_flagged"][bl, c] += int(t.exclude[bl, c, idx].sum())
                st["wrap_events"][bl, c] += int(np.abs(t.counts[bl, c, idx] - prev_count)[same].sum())
                self.last_scan[bl, c] = sc[-1]
                self.last_count[bl, c] = t.counts[bl, c, idx[-1]]
                self.last_seg[bl, c] = t.seg[bl, c, idx[-1]]
                self.last_suspect[bl, c] = t.suspect[bl, c, idx[-1]]

    def remember(self, t0, t1, counts, valid, seg) -> None:
        """Keep the aligned results of the last ``context`` samples up to t1 (arrays of [t0, t1))."""
        if self.t_start + self.counts.shape[-1] != t0:     # not contiguous: start afresh
            self.counts, self.valid, self.seg = (a[..., :0] for a in (self.counts, self.valid,
                                                                       self.seg))
            self.t_start = t0
        drop = max(0, self.counts.shape[-1] + (t1 - t0) - self.context)
        self.counts = keep_last(self.counts, counts, drop)
        self.valid = keep_last(self.valid, valid, drop)
        self.seg = keep_last(self.seg, seg, drop)
        self.t_start += drop


def segment_keys(seg: np.ndarray, scan: np.ndarray) -> np.ndarray:
    """scan index * SEGMENT_KEY + segment id per sample (-1 where no segment): the unit of the
    per-segment n0 step."""
    return np.where(seg >= 0, scan.astype(np.int64)[None, None, :] * SEGMENT_KEY + seg, -1)


def apply_segment_offsets(counts, keys, offsets: Dict[tuple, int]):
    """Counts with k added in every (baseline, correlation, segment) of ``offsets``.

    Adding k to the wrap count of a segment adds 2 pi eps k to its PWC output
    (and R 2 pi k = 2 pi eps k mod 2 pi to CWU): the per-segment n0 step.  One
    sorted look-up per series, whatever the number of segments.
    """
    if not offsets:
        return counts
    per_series: Dict[tuple, list] = {}
    for (b, c, key), k in offsets.items():
        if k:
            per_series.setdefault((int(b), int(c)), []).append((int(key), int(k)))
    if not per_series:
        return counts
    out = counts.copy()
    for (b, c), items in per_series.items():
        items.sort()
        table = np.array([key for key, _ in items], np.int64)
        values = np.array([k for _, k in items], np.int64)
        series = keys[b, c]
        pos = np.minimum(np.searchsorted(table, series), table.size - 1)
        out[b, c] += np.where(table[pos] == series, values[pos], 0)
    return out


def jump_list(jumps, times, corr_names, t_first: float) -> list:
    """Report rows of (correlation, time index, size in rad) jumps."""
    return [{"correlation": corr_names[c], "time": float(times[t]),
             "time_from_start_s": float(times[t] - t_first), "size_deg": math.degrees(size)}
            for c, t, size in jumps]


def baseline_report(stats: Stats, times, baseline_names, corr_names) -> list:
    """Per-baseline confidence numbers (summed and per correlation) and jump lists."""
    t_first = float(times[0]) if times.size else 0.0
    out = []
    for bl, name in enumerate(baseline_names):
        entry = {"baseline": name}
        for k in Stats.KEYS:
            entry[k] = int(stats.per_series[k][bl].sum())
        entry["per_correlation"] = {
            cn: {k: int(stats.per_series[k][bl, c]) for k in Stats.KEYS}
            for c, cn in enumerate(corr_names)}
        entry["jump_list"] = jump_list([(c, t, s) for b, c, t, s in stats.jumps if b == bl],
                                       times, corr_names, t_first)
        out.append(entry)
    return out
