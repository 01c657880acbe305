"""The n0 step of ``--reference-table``: an integer per antenna, receptor and segment.

Each antenna's solution series is counted from its first solution, and after a scan
change or a long gap (a *segment*) its count restarts on the branch nearest the last
phase (hitops/solutions/wraps.py): the unwrapped phase u_p of segment s is the true one
minus 2*pi*m_{p,s} for an unknown integer.  On target channel k that leaves
2*pi*R_k*(m_p - m_q) on baseline p-q, constant within the segment: per scan the column
is coherent, across scans it is not (measured on the demo scene: 0.98-0.99 per scan,
0.24-0.57 over the track on 9 of 10 baselines).

As with the antenna tracker (:mod:`hitops.calibrate.n0.antenna`), the integers are
solved per (field, receptor) on the 2*pi*eps*k lattice with every baseline at once
(:func:`hitops.calibrate.n0.lattice.solve_lattice`; nodes are (antenna, segment), edges
the baseline segments, z_e the sum of exp(i (Phi_model - Phi_out)) over the edge's
samples and channels of one target window, eps that window's R_c - floor(R_c)), so
closure phases are kept; the reference antenna's segments are the gauge (k = 0).  The
model is ``--offset-model point`` (phase 0), a model column, or
``--offset-reference-column`` (a calibrated column).  The integers are then taken out of
every window of the field: phase R_c*2*pi*m and delay m/nu_ref per solution of the
segment, so the column and the ``--caltable`` table carry the same correction.

Limit: the lattice values of k and k + q (eps = p/q) coincide at the window centre and
the search keeps the smallest |k|; across a window of bandwidth B they differ by a phase
slope of 2*pi*B*q/nu_ref (one turn over 2 GHz for q = 43 at 86 GHz), so a segment whose
true integer lies beyond q/2 of the first segment's leaves that slope in its channels.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np

from ...kernels.distinct import unique_rows
from ...solutions.api import PreparedTransfer
from ...solutions.transfer import TargetWindow
from .channel_lattice import solve_channels
from .lattice import solve_lattice

#: key of one baseline segment's sum: (series, receptor, segment, ant1, ant2)
EdgeKey = Tuple[int, int, int, int, int]


def series_of(prepared: PreparedTransfer, window_index: int) -> int:
    """The reference series (field) a transferred window comes from (windows are field-major)."""
    return window_index // len(prepared.target_centres_hz)


def segment_of(prepared: PreparedTransfer, series: int, times: np.ndarray) -> np.ndarray:
    """Segment index of each time: that of the last solution at or before it (the first's before)."""
    u = prepared.unwrapped[series]
    seg = np.cumsum(u.new_segment) - 1
    idx = np.clip(np.searchsorted(u.source.times, times, side="right") - 1, 0, seg.size - 1)
    return seg[idx]


def solve_windows(prepared: PreparedTransfer) -> Dict[int, int]:
    """The target window each series is solved on: its first (its R_c gives eps)."""
    chosen: Dict[int, int] = {}
    for j in range(len(prepared.targets)):
        chosen.setdefault(series_of(prepared, j), j)
    return chosen


def accumulate(sums: Dict[EdgeKey, List], prepared: PreparedTransfer, window_index: int,
               rows: np.ndarray, cols: Dict, out: np.ndarray, ok: np.ndarray,
               model_phase, receptors: np.ndarray) -> None:
    """Add one chunk's rows of the solve window to the per-channel edge sums (parallel hands)."""
    series = series_of(prepared, window_index)
    n_rec = prepared.targets[window_index].phase.shape[2]
    seg = segment_of(prepared, series, cols["TIME"][rows])
    keys = np.stack([seg, cols["ANTENNA1"][rows], cols["ANTENNA2"][rows]], axis=1)
    # (1 s per 10^6 rows through np.unique(axis=0); the same rows and order, 20x faster)
    uniq, inv = unique_rows(keys)
    mismatch = np.exp(1j * (model_phase - np.angle(out)))
    for c, (ra, rb) in enumerate(np.minimum(receptors, n_rec - 1)):
        if ra != rb:
            continue
        z = np.zeros((uniq.shape[0], out.shape[1]), np.complex128)
        n = np.zeros((uniq.shape[0], out.shape[1]), np.int64)
        np.add.at(z, inv, np.where(ok[:, :, c], mismatch[:, :, c], 0))
        np.add.at(n, inv, ok[:, :, c])
        for (s, p, q), zz, nn in zip(uniq.tolist(), z, n):
            entry = sums.setdefault((series, int(ra), s, p, q), [0j, 0])
            entry[0] = entry[0] + zz
            entry[1] = entry[1] + nn


@dataclass(frozen=True)
class TableOffsets:
    """The solved integers: {(series, receptor, antenna, segment): m} and the report's entries."""

    k: Dict[Tuple[int, int, int, int], int]
    solves: List[dict]


def _solve_one(n_nodes, a, b, z, n, ratios, max_k, gauge):
    """(k per node, score, samples, method): the lattice on one channel, else per channel."""
    if z.shape[1] == 1:
        sol = solve_lattice(n_nodes, a, b, z[:, 0], n[:, 0], ratios[0] - math.floor(ratios[0]),
                            max_k, gauge_order=gauge)
        return sol.k, sol.score, sol.samples, sol.method
    sol = solve_channels(n_nodes, a, b, z, n, ratios, max_k, gauge)
    return sol.k, sol.score, sol.samples, sol.method


def solve(prepared: PreparedTransfer, sums: Dict[EdgeKey, List], max_k: int,
          antenna_names, chan_freq) -> TableOffsets:
    """One solve per (series, receptor) over its baseline segments; ``chan_freq``: per
    spectral window of the target, its channel frequencies (Hz)."""
    k_out: Dict[Tuple[int, int, int, int], int] = {}
    solves = []
    windows = solve_windows(prepared)
    for (series, rec) in sorted({(key[0], key[1]) for key in sums}):
        edges = [(key, v) for key, v in sums.items() if key[:2] == (series, rec)]
        nodes: Dict[Tuple[int, int], int] = {}
        for (_, _, s, p, q), _ in edges:
            nodes.setdefault((p, s), len(nodes))
            nodes.setdefault((q, s), len(nodes))
        window = prepared.targets[windows[series]]
        ratios = np.asarray(chan_freq[window.spw], float) / prepared.unwrapped[series].source.ref_freq_hz
        refant = window.refant[window.refant >= 0]
        gauge = [v for (ant, _), v in nodes.items() if refant.size and ant == refant[0]]
        k, score, samples, method = _solve_one(
            len(nodes), [nodes[(p, s)] for (_, _, s, p, _), _ in edges],
            [nodes[(q, s)] for (_, _, s, _, q), _ in edges],
            np.array([v[0] for _, v in edges]), np.array([v[1] for _, v in edges]),
            ratios, int(max_k), gauge)
        for (ant, s), v in nodes.items():
            k_out[(series, rec, ant, s)] = int(k[v])
        solves.append({"field": window.field, "receptor": rec, "spw": window.spw,
                       "method": method, "samples": samples,
                       "mean_cos_mismatch": score / max(samples, 1),
                       "k": {f"{antenna_names[ant]}/segment {s}": int(k[v])
                             for (ant, s), v in sorted(nodes.items())}})
    return TableOffsets(k_out, solves)


def _shifted(window: TargetWindow, turns: np.ndarray, ref_freq_hz: float) -> TargetWindow:
    """The window with u - 2*pi*turns: phase at its centre and phase delay shifted."""
    ratio = window.centre_hz / ref_freq_hz
    return dataclasses.replace(window, phase=window.phase - 2 * math.pi * ratio * turns,
                               delay_s=window.delay_s - turns / ref_freq_hz)


def apply_offsets(prepared: PreparedTransfer, offsets: TableOffsets) -> PreparedTransfer:
    """Every transferred window with its series' integers taken out, segment by segment."""
    targets = []
    for j, window in enumerate(prepared.targets):
        series = series_of(prepared, j)
        seg = segment_of(prepared, series, window.times)
        turns = np.zeros(window.phase.shape)
        for (s_series, rec, ant, s), m in offsets.k.items():
            if s_series == series and m:
                turns[seg == s, ant, rec] = m
        targets.append(_shifted(window, turns, prepared.unwrapped[series].source.ref_freq_hz))
    return dataclasses.replace(prepared, targets=tuple(targets))
