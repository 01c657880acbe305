"""The n0 step of the antenna tracker: integers per antenna and segment on the 2 pi eps k lattice.

With the antenna tracker a count error k_p of antenna p enters baseline p-q as
2 pi eps (k_p - k_q).  Per (correlation, scan) the antenna segments are the
nodes and the baseline segments the edges of one
:func:`hitops.calibrate.n0.lattice.solve_lattice`; with both parallel hands
tied by the reference band (:mod:`hitops.calibrate.n0.hands`) the two hands of
a scan are one solve.  :func:`antenna_offsets` builds the solves
(:func:`_unit_graph`), measures the hands' instrumental phase difference
(:func:`_hand_rotation`), solves each (:func:`_solve_unit`) and describes the
result for the report (:func:`_series_entries`, :func:`_antenna_entries`,
:func:`_solve_entries`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from ...tracking.state import PAIR_KEY, SEGMENT_KEY
from .baseline import WindowRatios, canonical_k, choose_channel_offset, choose_offset
from .hands import HandPhases, hand_ties, parallel_hand_pair, phase_sync
from .lattice import LatticeSolution, solve_lattice


class Edge(NamedTuple):
    """One baseline segment: an edge between its two antennas' segments (nodes)."""

    corr: int
    scan: int            # scan index
    baseline: int
    key: int             # the segment key of the first pass's sums
    node_a: int          # the node of ant1's segment
    node_b: int          # the node of ant2's segment
    z: complex           # sum of exp(i (Phi_model - Phi_out)) over its samples; across a
                         # window's channels, (n_chan,) one sum per channel
    n: int               # its samples (over all channels)


@dataclass
class SolveUnit:
    """One lattice solve: a (correlation, scan), or both parallel hands of one scan.

    ``nodes``: (correlation, antenna, segment) -> node index; ``group``: the
    solve variable of each node (a node of the second hand tied to the first
    hand shares its variable); ``offset``: the integer each node adds to its
    variable (-j for a tied node: k1 - k2 = j).
    """

    scan: int
    corrs: List[int]
    nodes: Dict[Tuple[int, int, int], int]
    group: np.ndarray
    offset: np.ndarray
    edges: List[Edge]

    @property
    def joint(self) -> bool:
        return len(self.corrs) == 2


@dataclass
class AntennaOffsets:
    """The antenna n0 step's result.

    ``segment_k``: {(baseline, correlation, key): k_p - k_q} to add to the baseline
    wrap counts; ``antennas``: one report entry per antenna segment; ``solves``: one
    per solve and component (a joint solve is listed under each hand);
    ``series``: one per baseline segment (its k and the mismatch left).
    """

    segment_k: Dict[tuple, int] = field(default_factory=dict)
    antennas: List[dict] = field(default_factory=list)
    solves: List[dict] = field(default_factory=list)
    series: List[dict] = field(default_factory=list)


@dataclass(frozen=True)
class LatticeProblem:
    """What every solve of one :func:`antenna_offsets` call shares: the group's baselines
    (``ant1``, ``ant2``: antenna indices), names, scan numbers, eps, the candidate bound
    and ambiguity, the reference antennas in order of preference, the segment key of the
    sums, and across a wide window its per-channel ratios.  ``pair`` is set by
    :func:`antenna_offsets` (the parallel hands solved together)."""

    ant1: np.ndarray
    ant2: np.ndarray
    antenna_names: Sequence[str]
    baseline_names: Sequence[str]
    corr_names: Sequence[str]
    scans: np.ndarray
    eps: float
    max_k: int
    ambiguity_deg: float
    refants: Tuple[int, ...] = ()
    segment_key: int = int(SEGMENT_KEY)
    window: Optional[WindowRatios] = None   # the n0 step across a window's channels
    pair: Optional[Tuple[int, int]] = None  # the parallel hands solved together, or None

    @property
    def two_pi_eps(self) -> float:
        return 2 * math.pi * self.eps

    def lift(self, k):
        """exp(i 2 pi eps k), or per channel exp(i 2 pi R_j k) (k scalar or (n,))."""
        if self.window is None:
            return np.exp(1j * self.two_pi_eps * k)
        return self.window.turns(k)

    def shift(self, d):
        """exp(-i 2 pi eps d), or per channel exp(-i 2 pi R_j d): an edge's sum after d."""
        if self.window is None:
            return np.exp(-1j * self.two_pi_eps * d)
        return np.conj(self.window.turns(d))

    def total(self, z) -> complex:
        """An edge sum as one number: itself, or summed over the channels."""
        return complex(z) if self.window is None else complex(np.sum(z))

    def choose(self, w, n: int, k: int):
        """Candidate ``k`` described against the sum ``w`` (:func:`choose_offset`, or across
        the channels :func:`choose_channel_offset`)."""
        if self.window is None:
            return choose_offset(w, n, self.eps, self.max_k, self.ambiguity_deg, k=k)
        return choose_channel_offset(w, n, self.window, self.max_k, self.ambiguity_deg, k=k)

    def canonical(self, k: int) -> int:
        """The smallest equivalent |k| on one channel; across channels k itself."""
        return canonical_k(k, self.eps, self.max_k) if self.window is None else int(k)


def antenna_offsets(seg_sums, antenna_corrs, problem: LatticeProblem,
                    hands: Optional[HandPhases] = None) -> AntennaOffsets:
    """The n0 step of the antenna tracker: integers per antenna and segment on the lattice.

    ``seg_sums``: {(baseline, correlation, key): (z, n)} with z the sum of
    exp(i (Phi_model - Phi_out)) over the samples of that baseline segment
    (:func:`hitops.kernels.segments.segment_run_sums`), key = scan index *
    ``segment_key`` + sp * PAIR_KEY + sq for the correlations in ``antenna_corrs``.
    The reference antenna's segment (first of ``refants`` present, else the node with
    most samples) is the gauge, k = 0.

    ``hands``: with it and two parallel hands, the hands are solved together: each
    antenna segment of one hand is tied to the other hand's segment it overlaps
    (:func:`hitops.calibrate.n0.hands.hand_ties`, k1 - k2 = j from the reference band
    alone), the second hand's edges are rotated by the antenna-based phase difference
    between the hands measured over the whole track (instrumental R-L phases), and one
    lattice solve per scan uses the samples of both hands: twice the data per integer.

    ``window``: the sums are per target channel ((n_chan,) arrays) and the integers are
    chosen across them (k and k + 43 differ across a wide window; docs/wideband.md).
    """
    groups = _sums_by_solve(seg_sums, antenna_corrs, problem.segment_key)
    problem = dataclasses.replace(
        problem, refants=tuple(int(r) for r in problem.refants),
        pair=parallel_hand_pair(problem.corr_names, antenna_corrs) if hands is not None else None)
    tie = _hand_links(problem.pair, hands)
    units = [_unit_graph(unit, groups, tie, problem)
             for unit in _solve_units(groups, problem.pair, {key[0] for key in tie})]
    rot = np.ones(len(problem.antenna_names), np.complex128)
    if problem.pair is not None and any(u.joint for u in units):
        rot = _hand_rotation(units, problem)
    result = AntennaOffsets()
    for unit in units:
        _solve_unit(unit, rot, problem, result)
    return result


def _sums_by_solve(seg_sums, antenna_corrs, segment_key: int):
    """{(correlation, scan index): [(baseline, key, z, n)]} of the antenna correlations."""
    groups = {}
    for (b, c, key), (z, n) in seg_sums.items():
        if c not in antenna_corrs:
            continue
        groups.setdefault((int(c), int(key // segment_key)), []).append((int(b), int(key), z, int(n)))
    return groups


def _hand_links(pair, hands: Optional[HandPhases]) -> Dict[tuple, tuple]:
    """(scan, antenna, segment in the second hand) -> (segment in the first, j)."""
    tie = {}
    if pair is not None:
        for (s, p, a, b), (j, _) in hand_ties(hands.phase, hands.segment,
                                               hands.scan_of_time, *pair).items():
            tie[(s, p, b)] = (a, j)
    return tie


def _solve_units(groups, pair, tied_scans) -> List[List[tuple]]:
    """The (correlation, scan) of each solve: one, or both hands of a tied scan."""
    units, done = [], set()
    for (c, s) in sorted(groups):
        if (c, s) in done:
            continue
        if pair is not None and c in pair and (pair[0], s) in groups and (pair[1], s) in groups \
                and s in tied_scans:
            units.append([(pair[0], s), (pair[1], s)])
            done.update({(pair[0], s), (pair[1], s)})
        else:
            units.append([(c, s)])
            done.add((c, s))
    return units


def _unit_graph(unit, groups, tie, problem: LatticeProblem) -> SolveUnit:
    """Nodes (c, p, seg), their solve variable and offset, and the unit's edges."""
    nodes, edges = {}, []
    s = unit[0][1]
    for c, _ in unit:
        for b, key, zz, nn in groups[(c, s)]:
            seg = key % problem.segment_key
            va = nodes.setdefault((c, int(problem.ant1[b]), seg // PAIR_KEY), len(nodes))
            vb = nodes.setdefault((c, int(problem.ant2[b]), seg % PAIR_KEY), len(nodes))
            edges.append(Edge(c, s, b, key, va, vb, complex(zz) if problem.window is None
                              else np.asarray(zz, np.complex128), nn))
    group = np.full(len(nodes), -1, np.int64)
    offset = np.zeros(len(nodes), np.int64)
    pair = problem.pair
    second = pair[1] if len(unit) == 2 else None
    n_groups = 0
    for (c, p, sp), v in nodes.items():
        if c != second:
            group[v] = n_groups
            n_groups += 1
    for (c, p, sp), v in nodes.items():
        if c != second:
            continue
        link = tie.get((s, p, sp))
        if link is not None and (pair[0], p, link[0]) in nodes:
            # k in the second hand = k in the first - j (k1 - k2 = j)
            group[v] = group[nodes[(pair[0], p, link[0])]]
            offset[v] = -link[1]
        else:
            group[v] = n_groups
            n_groups += 1
    return SolveUnit(scan=s, corrs=[c for c, _ in unit], nodes=nodes, group=group,
                     offset=offset, edges=edges)


def _hand_rotation(units: List[SolveUnit], problem: LatticeProblem) -> np.ndarray:
    """The hands' antenna-based phase difference over the whole track: unit phasors per
    antenna (:func:`hitops.calibrate.n0.hands.phase_sync` of the products of the two
    hands' edge sums), applied to the second hand's edges."""
    first_hand, second_hand = problem.pair
    n_ant = len(problem.antenna_names)
    h = np.zeros((n_ant, n_ant), np.complex128)
    for unit in units:
        if not unit.joint:
            continue
        group, offset = unit.group, unit.offset
        first = {}
        for e in unit.edges:
            if e.corr == first_hand:
                first[(e.baseline, group[e.node_a], group[e.node_b])] = e.z
        for e in unit.edges:
            z1 = (first.get((e.baseline, group[e.node_a], group[e.node_b]))
                  if e.corr == second_hand else None)
            if z1 is None:
                continue
            z2 = e.z * problem.shift(offset[e.node_a] - offset[e.node_b])
            p, q = int(problem.ant1[e.baseline]), int(problem.ant2[e.baseline])
            h[p, q] += problem.total(z1 * np.conj(z2))
            h[q, p] += problem.total(np.conj(z1) * z2)
    return phase_sync(h)


def _solve_unit(unit: SolveUnit, rot: np.ndarray, problem: LatticeProblem,
                result: AntennaOffsets) -> None:
    """One lattice solve, its integers per node, and its report entries added to ``result``."""
    group, offset, edges = unit.group, unit.offset, unit.edges
    ant1, ant2 = problem.ant1, problem.ant2
    n_groups = int(group.max()) + 1 if group.size else 0
    ga = np.array([group[e.node_a] for e in edges], np.int64)
    gb = np.array([group[e.node_b] for e in edges], np.int64)
    zrot = np.array([e.z * problem.shift(offset[e.node_a] - offset[e.node_b])
                     * ((rot[int(ant1[e.baseline])] * np.conj(rot[int(ant2[e.baseline])]))
                        if unit.joint and e.corr == problem.pair[1] else 1.0)
                     for e in edges], np.complex128)
    n = np.array([e.n for e in edges], np.int64)
    gauge_order = []
    for r in problem.refants:
        for (c, p, sp) in sorted(unit.nodes):
            if p == r and int(group[unit.nodes[(c, p, sp)]]) not in gauge_order:
                gauge_order.append(int(group[unit.nodes[(c, p, sp)]]))
    sol = solve_lattice(n_groups, ga, gb, zrot, n, problem.eps, problem.max_k,
                        gauge_order=gauge_order, window=problem.window)
    k_node = np.array([problem.canonical(int(sol.k[group[v]] + offset[v]))
                       for v in range(len(unit.nodes))], np.int64)
    node_ph = problem.lift(k_node)
    hands_label = "+".join(problem.corr_names[c] for c in unit.corrs)
    _series_entries(unit, k_node, node_ph, problem, result)
    _antenna_entries(unit, sol, k_node, hands_label, problem, result)
    _solve_entries(unit, sol, ga, n, node_ph, hands_label, problem, result)


def _series_entries(unit: SolveUnit, k_node, node_ph, problem: LatticeProblem,
                    result: AntennaOffsets) -> None:
    """Each baseline segment's k = k_p - k_q and the mismatch left on it."""
    for e in unit.edges:
        d = int(k_node[e.node_a] - k_node[e.node_b])
        result.segment_k[(e.baseline, e.corr, e.key)] = d
        after = problem.total(e.z * np.conj(node_ph[e.node_a]) * node_ph[e.node_b])
        result.series.append({
            "baseline": problem.baseline_names[e.baseline], "correlation": problem.corr_names[e.corr],
            "scan": int(problem.scans[unit.scan]), "segment": int(e.key % problem.segment_key),
            "solve": "antenna", "k": d,
            "residual_deg": (math.degrees(abs(math.atan2(after.imag, after.real)))
                             if e.n else None),
            "coherence": float(abs(after) / e.n) if e.n else 0.0,
            "samples": int(e.n)})


def _antenna_entries(unit: SolveUnit, sol: LatticeSolution, k_node, hands_label: str,
                     problem: LatticeProblem, result: AntennaOffsets) -> None:
    """One entry per antenna segment: its k and how clearly the data chose it."""
    group, offset = unit.group, unit.offset
    gauges = set(int(g) for g in sol.gauge)
    for v, (c, p, seg) in enumerate(sorted(unit.nodes, key=unit.nodes.get)):
        g = int(group[v])
        # the group's sum over both hands, in this node's frame
        w = (complex(sol.node_sum[g]) if problem.window is None else sol.node_sum[g]) \
            * problem.lift(offset[v])
        choice = problem.choose(w, int(sol.node_count[g]), k=int(k_node[v]))
        entry = {"antenna": problem.antenna_names[p], "correlation": problem.corr_names[c],
                 "scan": int(problem.scans[unit.scan]), "segment": int(seg),
                 "reference": g in gauges,
                 # indices, for the gains of a calibration table (hitops/calibrate/gains.py)
                 "antenna_index": int(p), "correlation_index": int(c), "scan_index": int(unit.scan),
                 "baselines": int(sum(1 for e in unit.edges if v in (e.node_a, e.node_b)))}
        if unit.joint:
            entry["hands"] = hands_label
            entry["tied"] = bool(np.sum(group == g) > 1)
        if choice is None:
            entry.update(k=int(k_node[v]), samples=0, note="no sample to compare")
        else:
            entry.update(choice.as_dict())
            entry["margin_deg"] = (None if choice.runner_up_residual_deg is None else
                                   choice.runner_up_residual_deg - choice.residual_deg)
        result.antennas.append(entry)


def _solve_entries(unit: SolveUnit, sol: LatticeSolution, ga, n, node_ph, hands_label: str,
                   problem: LatticeProblem, result: AntennaOffsets) -> None:
    """One entry per connected component and hand: its gauge and the mismatch left."""
    group, edges = unit.group, unit.edges
    names = sorted(unit.nodes, key=unit.nodes.get)          # (c, p, seg) per node
    for comp, g0 in enumerate(sol.gauge):
        idx = [i for i in range(len(edges)) if sol.component[ga[i]] == comp]
        members = [v for v in range(len(names)) if sol.component[group[v]] == comp]
        ref_node = next((v for v in members if group[v] == g0), members[0] if members else 0)
        for c in unit.corrs:
            cidx = [i for i in idx if edges[i].corr == c]
            samples = int(sum(n[i] for i in cidx))
            after = [problem.total(edges[i].z * np.conj(node_ph[edges[i].node_a])
                                   * node_ph[edges[i].node_b]) for i in cidx]
            mism = np.array([math.degrees(math.atan2(a.imag, a.real)) for a in after])
            worst = int(np.argmax(np.abs(mism))) if cidx else None
            result.solves.append({
                "correlation": problem.corr_names[c], "scan": int(problem.scans[unit.scan]),
                "reference": (f"{problem.antenna_names[names[ref_node][1]]}/"
                              f"{names[ref_node][2]}"),
                "antenna_segments": sum(1 for v in members if names[v][0] == c),
                "baselines": len(cidx), "samples": samples,
                "method": sol.method, "hands": hands_label,
                "coherence": (float(sum(a.real for a in after) / samples) if samples else 0.0),
                "residual_rms_deg": float(np.sqrt(np.mean(mism ** 2))) if cidx else None,
                "worst_baseline": problem.baseline_names[edges[cidx[worst]].baseline] if cidx else None,
                "worst_residual_deg": float(abs(mism[worst])) if cidx else None})
