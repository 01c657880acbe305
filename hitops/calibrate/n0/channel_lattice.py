"""Integers per node on a many-channel window: the n0 step where one lattice phase is ambiguous.

The lattice solve of :mod:`hitops.calibrate.n0.lattice` compares one phase per edge with
the candidates 2*pi*eps*k.  On a window of many channels the integer j moves channel k by
2*pi*R_k*j: a phase at the centre *and* a slope across the window, and two integers whose
centre phases almost coincide (k and k + 39 differ by 4 deg at 227.1/86 GHz) differ in
slope.  Summed over channels first, the slope is lost and a coordinate descent on the
dense centre lattice stopped at such a neighbour (mean cos mismatch 0.965 instead of 1 on
a noise-free pair).  Here every channel keeps its own sum, and the score is

    S(j) = sum_e sum_k Re(z_{e,k} exp(-i 2 pi R_k (j_a - j_b))),

started from a spanning tree of per-edge best differences (each edge alone: the integer
difference whose phase and slope match its channels best, which is unique once the
slope is resolved) and improved by coordinate descent over |j| <= max_k.  Pure numpy;
nothing passed in is changed.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Sequence

import numpy as np

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ChannelSolution:
    k: np.ndarray          # (n_nodes,) int64
    score: float           # S at the solution
    samples: int           # samples over every edge and channel
    method: str


def _edge_differences(z: np.ndarray, ratios: np.ndarray, max_d: int) -> np.ndarray:
    """Per edge, the integer d (|d| <= max_d) maximising Re sum_k z_k exp(-i 2 pi R_k d)."""
    cand = np.arange(-max_d, max_d + 1)
    phasor = np.exp(-1j * TWO_PI * cand[:, None] * ratios[None, :])   # (n_cand, n_chan)
    return cand[np.argmax((z @ phasor.T).real, axis=1)]


def _tree_start(n_nodes, a, b, z, ratios, max_k, gauges) -> np.ndarray:
    """Node integers from the gauges along the strongest edges, each edge's best difference."""
    d = _edge_differences(z, ratios, 2 * max_k)
    order = np.argsort(-np.abs(z).sum(axis=1), kind="stable")
    adjacent = [[] for _ in range(n_nodes)]
    for e in order:
        adjacent[a[e]].append((b[e], e, -1))
        adjacent[b[e]].append((a[e], e, +1))
    j = np.zeros(n_nodes, np.int64)
    known = np.zeros(n_nodes, bool)
    for g in gauges:
        if known[g]:
            continue
        known[g] = True
        queue = deque([g])
        while queue:
            v = queue.popleft()
            for w, e, sign in adjacent[v]:
                if not known[w]:
                    # edge (a, b): j_a - j_b = d_e
                    j[w] = j[v] + sign * d[e]
                    known[w] = True
                    queue.append(w)
    return j


def _score(a, b, z, ratios, j) -> float:
    return float((z * np.exp(-1j * TWO_PI * (j[a] - j[b])[:, None] * ratios[None, :])).real.sum())


def solve_channels(n_nodes: int, edge_a, edge_b, edge_sums, edge_counts, ratios: Sequence[float],
                   max_k: int, gauge_nodes: Sequence[int], max_sweeps: int = 50) -> ChannelSolution:
    """Integers j per node maximising S(j); the gauge nodes (one per component) stay 0.

    ``edge_sums``: (n_edges, n_chan) complex, z_{e,k} = sum of exp(i (Phi_model - Phi_out))
    over the edge's samples of channel k; ``edge_counts``: (n_edges, n_chan) samples;
    ``ratios``: R_k = nu_k / nu_ref of the channels.
    """
    counts = np.asarray(edge_counts)
    used = counts.sum(axis=1) > 0          # an edge without samples says nothing
    a = np.asarray(edge_a, np.int64)[used]
    b = np.asarray(edge_b, np.int64)[used]
    z = np.asarray(edge_sums, np.complex128)[used]
    ratios = np.asarray(ratios, np.float64)
    gauges = list(dict.fromkeys(int(g) for g in gauge_nodes))
    # a component without a preferred gauge: its node with the most samples
    weight = np.zeros(n_nodes)
    np.add.at(weight, a, counts[used].sum(axis=1))
    np.add.at(weight, b, counts[used].sum(axis=1))
    j = _tree_start(n_nodes, a, b, z, ratios, max_k, gauges + list(np.argsort(-weight)))
    fixed = np.zeros(n_nodes, bool)
    fixed[gauges] = True
    cand = np.arange(-max_k, max_k + 1)
    phasor = np.exp(-1j * TWO_PI * cand[:, None] * ratios[None, :])      # (n_cand, n_chan)
    for _ in range(max_sweeps):
        changed = False
        for v in np.flatnonzero(~fixed):
            as_a, as_b = a == v, b == v
            # v as ANTENNA1: z e^{+i2piR j_b} e^{-i2piR c}; as ANTENNA2: conj of the same form
            wa = (z[as_a] * np.exp(1j * TWO_PI * j[b[as_a]][:, None] * ratios)).sum(axis=0)
            wb = (np.conj(z[as_b]) * np.exp(1j * TWO_PI * j[a[as_b]][:, None] * ratios)).sum(axis=0)
            best = cand[np.argmax((phasor @ (wa + wb)).real)]
            if best != j[v] and (phasor[best + max_k] @ (wa + wb)).real > \
                    (np.exp(-1j * TWO_PI * j[v] * ratios) @ (wa + wb)).real + 1e-9:
                j[v] = best
                changed = True
        if not changed:
            break
    return ChannelSolution(j, _score(a, b, z, ratios, j), int(counts.sum()),
                           "channel tree + descent")
