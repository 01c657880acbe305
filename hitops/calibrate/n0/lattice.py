"""The integer lattice solver of the antenna n0 offsets: k per node on the 2*pi*eps*k lattice.

With the antenna tracker a count error k_p of antenna p enters baseline p-q as
2*pi*eps*(k_p - k_q), constant over the samples where p and q stay in the same
tracking segments.  Given, per baseline and pair of antenna segments (an *edge*
between two *nodes*, a node being one antenna segment), the sum

    z_e = sum over samples of exp(i (Phi_model - Phi_out)),

adding the integer j_a to node a and j_b to node b turns the edge into
z_e * exp(-i 2 pi eps (j_a - j_b)).  :func:`solve_lattice` picks the integers
(|j| <= max_k, one *gauge* node per connected component fixed at 0, since a
common integer on every antenna changes no baseline) that maximise

    S(j) = sum_e Re(z_e exp(-i 2 pi eps (j_a - j_b))),

i.e. the calibrated phases best match the model on every baseline at once (the
sum of cos(mismatch) over samples, the circular-mean criterion of the paper's
n0 step summed over baselines).  Given the others, node v's best integer is the
lattice point 2 pi eps j nearest Arg(W_v) with

    W_v = sum_{e: a_e = v} z_e P_{b_e} + sum_{e: b_e = v} conj(z_e) P_{a_e},
    P_w = exp(i 2 pi eps j_w),

which is what :func:`node_sums` returns and what the report describes per node
(measured offset, residual, runner-up, margin).

Search: the lattice values are dense modulo 2 pi (8.37 deg apart for
eps = 29/43), so the candidates are |k| <= max_k with equivalent values (k and
k + 43 for eps = 29/43) merged onto the smallest |k|.  When the candidates of
the free nodes number at most ``exhaustive_limit`` combinations the search is
exhaustive (the global optimum); otherwise coordinate descent from two starts
(a maximum spanning tree of the edges grown from the gauge, and the rounded
leading eigenvector of the Hermitian edge matrix, the continuous phase
synchronisation) and the better end point is kept.  The kernels are numba.

Across a target window's channels (``window``, issue 26) an edge holds one sum per
channel, candidate j rotates channel c by 2 pi R_c j, and S sums over the channels:
every |j| <= max_k is then its own candidate (k and k + 43 differ across the window).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numba
import numpy as np

from .baseline import WindowRatios, channel_candidates

TWO_PI = 2.0 * math.pi
#: free-node candidate combinations searched exhaustively (43^3 = 79 507 for eps = 29/43)
EXHAUSTIVE_LIMIT = 250_000
#: two candidates whose lattice values differ by less than this (rad) are the same point
SAME_POINT = 1e-9


def _wrap(x):
    return (np.asarray(x) + math.pi) % TWO_PI - math.pi


def candidates(eps: float, max_k: int):
    """Distinct lattice points: (k int64, phasor complex128), smallest |k| first.

    k runs 0, -1, 1, -2, 2, ... up to |k| = max_k; a k whose 2 pi eps k equals an
    earlier one's modulo 2 pi (to 1e-9 rad) is dropped.
    """
    max_k = int(max_k)
    ks = [0]
    for m in range(1, max_k + 1):
        ks += [-m, m]
    ks = np.asarray(ks, np.int64)
    phase = _wrap(TWO_PI * float(eps) * ks)
    keep = []
    for i in range(ks.size):
        if all(abs(float(_wrap(phase[i] - phase[j]))) > SAME_POINT for j in keep):
            keep.append(i)
    keep = np.asarray(keep, np.int64)
    return ks[keep], np.exp(1j * phase[keep])


# The kernels below take the edge sums z (n_edges, n_chan) and the candidates' phasors
# (n_candidates, n_chan): one column for the lattice of one channel (2*pi*eps*k), one per
# target channel for the n0 step across a window (2*pi*R_j*k, hitops/calibrate/n0/baseline.py);
# a score is summed over the channels.


@numba.njit(cache=True, nogil=True)
def _score(a, b, z, phasor, u):
    s = 0.0
    for e in range(a.shape[0]):
        for ch in range(z.shape[1]):
            s += (z[e, ch] * np.conj(phasor[u[a[e]], ch]) * phasor[u[b[e]], ch]).real
    return s


@numba.njit(cache=True, nogil=True)
def _node_sum(v, a, b, z, phasor, u):
    w = np.zeros(z.shape[1], np.complex128)
    for e in range(a.shape[0]):
        for ch in range(z.shape[1]):
            if a[e] == v:
                w[ch] += z[e, ch] * phasor[u[b[e]], ch]
            elif b[e] == v:
                w[ch] += np.conj(z[e, ch]) * phasor[u[a[e]], ch]
    return w


@numba.njit(cache=True, nogil=True)
def _fit(w, phasor, i):
    """Re(sum over channels of conj(P_i) w): how well candidate i explains the node sum w."""
    s = 0.0
    for ch in range(w.shape[0]):
        s += (np.conj(phasor[i, ch]) * w[ch]).real
    return s


@numba.njit(cache=True, nogil=True)
def _best_candidate(w, phasor):
    """Index of the candidate maximising Re(conj(P) w); ties to the earlier (smaller |k|)."""
    best = 0
    best_s = _fit(w, phasor, 0)
    for i in range(1, phasor.shape[0]):
        s = _fit(w, phasor, i)
        if s > best_s + 1e-12 * (1.0 + abs(best_s)):
            best_s = s
            best = i
    return best


@numba.njit(cache=True, nogil=True)
def _descent(a, b, z, phasor, u0, fixed, max_sweeps):
    """Coordinate descent over the free nodes from ``u0``; returns (u, sweeps)."""
    u = u0.copy()
    n = u.size
    for sweep in range(max_sweeps):
        changed = False
        for v in range(n):
            if fixed[v]:
                continue
            w = _node_sum(v, a, b, z, phasor, u)
            if not np.any(w != 0):
                continue
            best = _best_candidate(w, phasor)
            if best != u[v]:
                # move only on a strict gain (no cycling between equal points)
                old = _fit(w, phasor, u[v])
                new = _fit(w, phasor, best)
                if new > old + 1e-12 * (1.0 + abs(old)):
                    u[v] = best
                    changed = True
        if not changed:
            return u, sweep + 1
    return u, max_sweeps


@numba.njit(cache=True, nogil=True)
def _exhaustive(a, b, z, phasor, u0, free):
    """Every combination of candidates on the ``free`` nodes; the best (first on ties)."""
    u = u0.copy()
    m = phasor.shape[0]
    f = free.size
    digits = np.zeros(f, np.int64)
    for i in range(f):
        u[free[i]] = 0
    best_u = u.copy()
    best_s = _score(a, b, z, phasor, u)
    while True:
        i = 0
        while i < f:
            digits[i] += 1
            if digits[i] < m:
                break
            digits[i] = 0
            i += 1
        if i == f:
            break
        for k in range(f):
            u[free[k]] = digits[k]
        s = _score(a, b, z, phasor, u)
        if s > best_s + 1e-12 * (1.0 + abs(best_s)):
            best_s = s
            best_u[:] = u
    return best_u


@dataclass
class LatticeSolution:
    """The integers per node and what the report needs about them."""

    k: np.ndarray            # (n_nodes,) int64 integer added to each node's wrap count
    node_sum: np.ndarray     # (n_nodes,) complex128 W_v at the solution
    node_count: np.ndarray   # (n_nodes,) int64 samples on the node's edges
    edge_sum: np.ndarray     # (n_edges,) complex128 z_e after the solution
    component: np.ndarray    # (n_nodes,) int64 connected component of each node
    gauge: np.ndarray        # (n_components,) int64 node fixed at k = 0 in each component
    score: float             # sum_e Re(edge_sum): samples times the mean cos(mismatch)
    samples: int             # sum of the edge counts
    method: str              # 'exhaustive', 'descent' or 'trivial'


def _components(n_nodes, a, b):
    parent = list(range(n_nodes))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for p, q in zip(a.tolist(), b.tolist()):
        rp, rq = find(p), find(q)
        if rp != rq:
            parent[max(rp, rq)] = min(rp, rq)
    roots = np.array([find(v) for v in range(n_nodes)], np.int64)
    _, comp = np.unique(roots, return_inverse=True)
    return comp.ravel().astype(np.int64)


def _tree_start(n_nodes, a, b, z, phasor, gauges):
    """Maximum spanning tree from the gauges (strongest |z_e| first), each node set by its
    tree edge alone: the per-baseline estimate propagated outward."""
    u = np.zeros(n_nodes, np.int64)
    done = np.zeros(n_nodes, bool)
    done[gauges] = True
    order = np.argsort(-np.abs(z).sum(axis=1), kind="stable")
    progress = True
    while progress:
        progress = False
        for e in order:
            p, q = int(a[e]), int(b[e])
            if done[p] == done[q]:
                continue
            if done[p]:     # set q: maximise Re(z conj(P_p) P_q) -> P_q near arg(conj(z) P_p)
                u[q] = _best_candidate(np.conj(z[e]) * phasor[u[p]], phasor)
                done[q] = True
            else:           # set p: P_p near arg(z P_q)
                u[p] = _best_candidate(z[e] * phasor[u[q]], phasor)
                done[p] = True
            progress = True
            break
    return u


def _eigen_start(n_nodes, a, b, z, phasor, comp, gauges):
    """Leading eigenvector of H (H_ab = z_e / 2 + conj for the transpose), per component
    phase-referenced to its gauge and rounded to the nearest lattice point.  Across a
    window's channels the relaxation uses the middle channel: its candidates nearest the
    eigenvector's phase (the smallest |k| among equals) start the descent."""
    mid = z.shape[1] // 2
    h = np.zeros((n_nodes, n_nodes), np.complex128)
    for e in range(a.size):
        # S = Re(sum_e z_e conj(x_a) x_b) = x^H H x with H Hermitian
        h[a[e], b[e]] += 0.5 * z[e, mid]
        h[b[e], a[e]] += 0.5 * np.conj(z[e, mid])
    u = np.zeros(n_nodes, np.int64)
    for c, g in enumerate(gauges):
        nodes = np.flatnonzero(comp == c)
        if nodes.size < 2:
            continue
        _, vecs = np.linalg.eigh(h[np.ix_(nodes, nodes)])
        x = vecs[:, -1]
        ref = x[nodes.tolist().index(int(g))]
        if ref == 0:
            continue
        x = x * np.conj(ref) / abs(ref)
        for i, v in enumerate(nodes):
            if x[i] != 0:
                w = np.zeros(z.shape[1], np.complex128)
                w[mid] = x[i] / abs(x[i])
                u[v] = _best_candidate(w, phasor)
    return u


def _descent_with_gauge_moves(a, b, z, ks, phasor, u0, fixed, comp, gauges, eps, max_sweeps,
                              per_channel: bool):
    """Coordinate descent in which a gauge may move too.

    Moving the gauge alone is the same as moving every other node of its component the
    opposite way, which single-node descent cannot do: a gauge whose own measurement
    sits off its lattice point would otherwise hold the whole component on the wrong
    side.  When the gauge's best point is not its own, every other node of the
    component is shifted by minus that integer (if each shifted value is a candidate)
    and the descent goes on; the gauge stays at 0.  ``per_channel``: the candidates are
    every integer (a window's channels tell them all apart), found by value.
    """
    phase = np.angle(phasor)
    u = u0.copy()
    for _ in range(max_sweeps):
        u, _ = _descent(a, b, z, phasor, u, fixed, max_sweeps)
        moved = False
        for c, g in enumerate(gauges):
            w = _node_sum(int(g), a, b, z, phasor, u)
            if not np.any(w != 0):
                continue
            best = _best_candidate(w, phasor)
            if best == u[g] or not (_fit(w, phasor, best)
                                    > _fit(w, phasor, u[g]) * (1 + 1e-12) + 1e-12):
                continue
            shift = int(ks[best] - ks[u[g]])
            members = np.flatnonzero((comp == c) & (np.arange(u.size) != g))
            new = u.copy()
            ok = True
            for v in members:
                if per_channel:
                    hit = np.flatnonzero(ks == ks[u[v]] - shift)
                else:
                    target = float(_wrap(TWO_PI * eps * (ks[u[v]] - shift)))
                    hit = np.flatnonzero(np.abs(_wrap(phase[:, 0] - target)) < 1e-7)
                if not hit.size:
                    ok = False
                    break
                new[v] = hit[0]
            if ok:
                u = new
                moved = True
        if not moved:
            break
    return u


def node_sums(a, b, z, phasor_of_node):
    """W_v of every node for node phasors ``phasor_of_node`` (exp(i 2 pi eps j_v); per
    channel: (n_nodes, n_chan) with ``z`` (n_edges, n_chan))."""
    w = np.zeros(phasor_of_node.shape, np.complex128)
    np.add.at(w, a, z * phasor_of_node[b])
    np.add.at(w, b, np.conj(z) * phasor_of_node[a])
    return w


def solve_lattice(n_nodes: int, edge_a, edge_b, edge_sum, edge_count, eps: float, max_k: int,
                  gauge_order: Optional[Sequence[int]] = None,
                  exhaustive_limit: int = EXHAUSTIVE_LIMIT, max_sweeps: int = 200,
                  window: Optional[WindowRatios] = None) -> LatticeSolution:
    """Integers j (|j| <= max_k) per node maximising sum_e Re(z_e exp(-i 2 pi eps (j_a - j_b))).

    ``edge_a``/``edge_b``: node indices of each edge (baseline p-q: a = p's segment,
    b = q's); ``edge_sum``: z_e = sum of exp(i (Phi_model - Phi_out)) over its
    samples; ``edge_count``: its samples.  ``gauge_order``: nodes preferred as the
    gauge (k = 0) of their component (the reference antenna's); otherwise the node
    with the most samples.  ``window``: the n0 step across a target window's channels;
    ``edge_sum`` is then (n_edges, n_chan), the score sum_e sum_j Re(z_ej exp(-i 2 pi R_j
    (j_a - j_b))), and every |j| <= max_k is a candidate of its own (the channels tell k
    from k + 43).  Pure: no input is changed.
    """
    a = np.asarray(edge_a, np.int64)
    b = np.asarray(edge_b, np.int64)
    z = np.asarray(edge_sum, np.complex128)
    cnt = np.asarray(edge_count, np.int64)
    if np.any(a == b):
        raise ValueError("an edge joins a node to itself")
    if window is None:
        ks, phasor = candidates(eps, max_k)
        z_cols, phasor_cols = z[:, None], phasor[:, None]
    else:
        ks = channel_candidates(max_k)
        phasor = phasor_cols = window.turns(ks)
        z_cols = z
    use = (cnt > 0) & np.any(z_cols != 0, axis=1)
    a, b, z_used = a[use], b[use], z_cols[use]
    node_count = np.zeros(n_nodes, np.int64)
    np.add.at(node_count, np.asarray(edge_a, np.int64), cnt)
    np.add.at(node_count, np.asarray(edge_b, np.int64), cnt)
    comp = _components(n_nodes, a, b)
    n_comp = int(comp.max()) + 1 if n_nodes else 0
    preferred = {int(v): i for i, v in enumerate(gauge_order or [])}
    gauges = np.zeros(n_comp, np.int64)
    for c in range(n_comp):
        nodes = np.flatnonzero(comp == c)
        ranked = sorted(nodes.tolist(), key=lambda v: (preferred.get(v, len(preferred)),
                                                        -node_count[v], v))
        gauges[c] = ranked[0]
    fixed = np.zeros(n_nodes, bool)
    fixed[gauges] = True
    free = np.flatnonzero(~fixed)
    # u: candidate index per node (0 is k = 0)
    if free.size == 0 or a.size == 0 or ks.size == 1:
        u = np.zeros(n_nodes, np.int64)
        method = "trivial"
    elif float(ks.size) ** free.size <= exhaustive_limit:
        u = _exhaustive(a, b, z_used, phasor_cols, np.zeros(n_nodes, np.int64), free)
        method = "exhaustive"
    else:
        best = None
        for start in (_tree_start(n_nodes, a, b, z_used, phasor_cols, gauges),
                      _eigen_start(n_nodes, a, b, z_used, phasor_cols, comp, gauges)):
            cand = _descent_with_gauge_moves(a, b, z_used, ks, phasor_cols, start, fixed, comp,
                                             gauges, eps, max_sweeps, window is not None)
            s = _score(a, b, z_used, phasor_cols, cand)
            if best is None or s > best[0] + 1e-12 * (1.0 + abs(best[0])):
                best = (s, cand)
        u = best[1]
        method = "descent"
    k = ks[u]
    node_ph = phasor[u]
    ea = np.asarray(edge_a, np.int64)
    eb = np.asarray(edge_b, np.int64)
    after = z * np.conj(node_ph[ea]) * node_ph[eb]
    return LatticeSolution(k=k.astype(np.int64), node_sum=node_sums(ea, eb, z, node_ph),
                           node_count=node_count, edge_sum=after, component=comp, gauge=gauges,
                           score=float(after.real.sum()), samples=int(cnt.sum()), method=method)
