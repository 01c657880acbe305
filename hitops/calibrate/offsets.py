"""The n0 offset step of PWC (paper, Results and discussion, eq. Delta_pwc).

PWC counts reference wraps from n'(t0) = 0; when the true count at the
first sample is n0 the output keeps a constant -2*pi*eps*n0.  Given a
reference calibration of the same target data (e.g. FF+SC CORRECTED_DATA),
the circular mean of exp(i*(Phi_ref - Phi_PWC)) estimates that constant, and
the candidate 2*pi*eps*k (|k| <= max_k) closest to it is added back.

The candidates are dense modulo 2*pi (eps = 29/43 puts them on an 8.37 deg
grid), so k is only trustworthy when the measured offset sits clearly
closer to one candidate than to any other: the choice is reported with its
residual and the runner-up, and flagged ambiguous otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, asdict

import numpy as np


@dataclass
class OffsetChoice:
    k: int                        # chosen n0 (offset added: 2*pi*eps*k)
    offset_deg: float             # 2*pi*eps*k wrapped, degrees
    measured_deg: float           # Arg of the circular mean, degrees
    residual_deg: float           # |measured - offset| wrapped, degrees
    runner_up_k: int | None       # best candidate with a different offset
    runner_up_residual_deg: float | None
    coherence: float              # |mean z|: 1 when the two calibrations agree perfectly
    samples: int
    ambiguous: bool

    def as_dict(self) -> dict:
        return asdict(self)


def _wrap(x):
    return (x + math.pi) % (2 * math.pi) - math.pi


def choose_offset(z_sum: complex, count: int, eps: float, max_k: int,
                  ambiguity_deg: float, k: int | None = None) -> OffsetChoice | None:
    """Pick k in [-max_k, max_k] whose 2*pi*eps*k is closest to Arg(z_sum).

    Ties go to the smallest |k|.  ``ambiguous`` when the runner-up residual is
    within ``ambiguity_deg`` of the best one.  None when there are no samples.
    ``k``: describe this candidate instead of choosing (the gauge of the antenna
    solve, fixed at 0): its residual, and the runner-up among the others.
    """
    if count <= 0 or z_sum == 0:
        return None
    measured = math.atan2(z_sum.imag, z_sum.real)
    ks = np.arange(-max_k, max_k + 1)
    ks = ks[np.argsort(np.abs(ks), kind="stable")]          # 0, -1, 1, -2, 2, ...
    offsets = np.array([_wrap(2 * math.pi * eps * k) for k in ks])
    residuals = np.abs(np.array([_wrap(measured - o) for o in offsets]))
    # first candidate within rounding of the minimum: the smallest |k| among candidates
    # that are the same offset modulo 2*pi (k and k + 43 for eps = 29/43)
    if k is None:
        best = int(np.flatnonzero(residuals <= residuals.min() + 1e-9)[0])
        best_k, best_off, best_res = int(ks[best]), offsets[best], residuals[best]
    else:
        # any integer (a hand tied to the other may sit beyond max_k)
        best_k = int(k)
        best_off = _wrap(2 * math.pi * eps * best_k)
        best_res = abs(_wrap(measured - best_off))
    distinct = np.abs(np.array([_wrap(o - best_off) for o in offsets])) > 1e-9
    runner_k = runner_res = None
    ambiguous = False
    if np.any(distinct):
        idx = np.flatnonzero(distinct)
        # the smallest |k| among runner-ups equal to rounding (k and k + 43 for 29/43)
        j = int(idx[np.flatnonzero(residuals[idx] <= residuals[idx].min() + 1e-9)[0]])
        runner_k = int(ks[j])
        runner_res = math.degrees(residuals[j])
        ambiguous = (runner_res - math.degrees(best_res)) < ambiguity_deg
    return OffsetChoice(k=best_k, offset_deg=math.degrees(best_off),
                        measured_deg=math.degrees(measured),
                        residual_deg=math.degrees(best_res), runner_up_k=runner_k,
                        runner_up_residual_deg=runner_res,
                        coherence=float(abs(z_sum) / count), samples=int(count),
                        ambiguous=bool(ambiguous))


# ----------------------------------------------------------------------------- the model

#: ``--offset-model point``: a point source at the phase centre (model phase 0 everywhere)
POINT_MODEL = "point"
#: antenna mode: a baseline's segment id is sp * PAIR_KEY + sq, sp and sq the aligned
#: segment ids of its two antennas (hitops.tracking.base.WrapTracker.track)
PAIR_KEY = 1_000_003


def is_point_model(offset_model) -> bool:
    return bool(offset_model) and str(offset_model).strip().lower() == POINT_MODEL


def parallel_hand_pair(corr_names, antenna_corrs):
    """The two parallel hands (RR and LL, or XX and YY) among ``antenna_corrs``; None otherwise."""
    hands = sorted(int(c) for c in antenna_corrs
                   if len(corr_names[c]) == 2 and corr_names[c][0] == corr_names[c][1])
    return tuple(hands) if len(hands) == 2 else None


#: a hand tie needs this fraction of the common samples to agree on j (a slip in one hand
#: splits them; its segment is then solved per hand)
TIE_AGREEMENT = 0.9


def hand_ties(antenna_phase, antenna_segment, scan_of_time, c1: int, c2: int,
              min_agreement: float = TIE_AGREEMENT) -> dict:
    """Integer relation between two hands' wrap counts per antenna, scan and segment pair.

    Both parallel hands see the same troposphere, so an antenna's tracked (unwrapped)
    reference phases in the two hands differ by a constant instrumental phase plus
    2 pi (m1 - m2), m the hands' count errors.  Per antenna the constant is taken as
    the circular mean of the difference over the whole track (c0), and per scan and
    pair of overlapping segments j = m1 - m2 is the most frequent
    round((phi1 - phi2 - c0) / 2 pi) over their common samples.  Only mutual best
    overlaps are tied (each segment with the other hand's segment it shares most
    samples with), and only when at least ``min_agreement`` of their common samples
    give that j (a slip in one hand inside the segment splits them).  A track-wide integer on top (the convention for c0) is a constant
    per antenna, which the hand rotation of :func:`antenna_offsets` absorbs.

    ``antenna_phase`` (n_ant, n_corr, n_time) float64 unwrapped antenna phases (NaN
    where unsolved), ``antenna_segment`` (n_ant, n_corr, n_time) int64 aligned segment
    ids (-1: none), ``scan_of_time`` (n_time,) scan index.  Returns {(scan, antenna,
    segment in c1, segment in c2): (j, common samples)}.  Pure.
    """
    phase = np.asarray(antenna_phase, np.float64)
    seg = np.asarray(antenna_segment, np.int64)
    scan = np.asarray(scan_of_time, np.int64)
    ties = {}
    for p in range(phase.shape[0]):
        ph1, ph2 = phase[p, c1], phase[p, c2]
        s1, s2 = seg[p, c1], seg[p, c2]
        ok = np.isfinite(ph1) & np.isfinite(ph2) & (s1 >= 0) & (s2 >= 0)
        if not ok.any():
            continue
        d = ph1[ok] - ph2[ok]
        c0 = math.atan2(float(np.sin(d).sum()), float(np.cos(d).sum()))
        j = np.rint((d - c0) / (2 * math.pi)).astype(np.int64)
        # (scan, seg1, seg2, j) packed into one int64 per sample, counted with one sort
        cols = [scan[ok], s1[ok], s2[ok], j]
        lo = [int(c.min()) for c in cols]
        span = [int(c.max()) - l + 1 for c, l in zip(cols, lo)]
        packed = np.zeros(j.size, np.int64)
        for c, l, w in zip(cols, lo, span):
            packed = packed * w + (c - l)
        uniq, cnt = np.unique(packed, return_counts=True)
        unpacked = []
        for w, l in zip(reversed(span), reversed(lo)):
            unpacked.append(uniq % w + l)
            uniq = uniq // w
        rows = np.stack(unpacked[::-1], axis=1)
        pairs = {}
        for (s, a, b, jj), n in zip(rows.tolist(), cnt.tolist()):
            total, best_j, best_n = pairs.get((s, a, b), (0, 0, -1))
            pairs[(s, a, b)] = (total + n, jj if n > best_n else best_j, max(n, best_n))
        first, second = {}, {}
        for (s, a, b), (total, _, _) in pairs.items():
            if total > first.get((s, a), (0, None))[0]:
                first[(s, a)] = (total, b)
            if total > second.get((s, b), (0, None))[0]:
                second[(s, b)] = (total, a)
        for (s, a, b), (total, jj, n_j) in pairs.items():
            if first[(s, a)][1] == b and second[(s, b)][1] == a and n_j >= min_agreement * total:
                ties[(int(s), int(p), int(a), int(b))] = (int(jj), int(total))
    return ties


def _canonical_k(k: int, eps: float, max_k: int) -> int:
    """The smallest |k'| <= max_k with 2 pi eps k' = 2 pi eps k (mod 2 pi); k if none."""
    m = 0
    while m <= max_k:
        for kk in ((0,) if m == 0 else (-m, m)):
            if abs(_wrap(2 * math.pi * eps * (kk - k))) < 1e-9:
                return kk
        m += 1
    return int(k)


def _phase_sync(h) -> np.ndarray:
    """Unit phasors x with h[p, q] ~ |h| x_p conj(x_q): the leading eigenvector of the
    Hermitian ``h``, per connected block; 1 where an antenna has no entry."""
    n = h.shape[0]
    x = np.ones(n, np.complex128)
    used = np.flatnonzero(np.abs(h).sum(axis=1) > 0)
    if used.size < 2:
        return x
    _, vecs = np.linalg.eigh(h[np.ix_(used, used)])
    v = vecs[:, -1]
    mag = np.abs(v)
    v = np.where(mag > 0, v / np.where(mag > 0, mag, 1), 1)
    x[used] = v * np.conj(v[0])
    return x


def antenna_offsets(seg_sums, antenna_corrs, ant1, ant2, antenna_names, baseline_names,
                    corr_names, scans, eps: float, max_k: int, ambiguity_deg: float,
                    refants=(), segment_key: int = 1 << 32, hands=None):
    """The n0 step of the antenna tracker: integers per antenna and segment on the lattice.

    ``seg_sums``: {(baseline, correlation, key): (z, n)} with z the sum of
    exp(i (Phi_model - Phi_out)) over the samples of that baseline segment
    (:func:`hitops.calibrate.lattice.segment_run_sums`), key = scan index *
    ``segment_key`` + sp * PAIR_KEY + sq for the correlations in ``antenna_corrs``.
    Per (correlation, scan) the antenna segments are the nodes and the baseline
    segments the edges of one :func:`hitops.calibrate.lattice.solve_lattice`; the
    reference antenna's segment (first of ``refants`` present, else the node with
    most samples) is the gauge, k = 0.

    ``hands``: the reference band's tracked antenna phases, a dict with ``phase``
    (n_ant, n_corr, n_time), ``segment`` (n_ant, n_corr, n_time) and
    ``scan_of_time`` (the antenna tracker's ``antenna_phase``/``antenna_segment``).
    With it and two parallel hands, the hands are solved together: each antenna
    segment of one hand is tied to the other hand's segment it overlaps
    (:func:`hand_ties`, k1 - k2 = j from the reference band alone), the second hand's
    edges are rotated by the antenna-based phase difference between the hands
    measured over the whole track (instrumental R-L phases; :func:`_phase_sync` of
    the products of the two hands' edge sums), and one lattice solve per scan uses
    the samples of both hands: twice the data per integer.

    Returns (segment_k, antennas, solves, series): segment_k {(b, c, key): k_p - k_q}
    to add to the baseline wrap counts; one report entry per antenna segment (k,
    measured offset, residual, runner-up, margin, coherence, samples, reference,
    ambiguous, ``hands`` when solved with both), one per solve (component; a joint
    solve is listed under each hand), and one per baseline segment (its k and the
    mismatch left).
    """
    from .lattice import node_sums, solve_lattice

    groups = {}
    for (b, c, key), (z, n) in seg_sums.items():
        if c not in antenna_corrs:
            continue
        groups.setdefault((int(c), int(key // segment_key)), []).append((int(b), int(key), z, int(n)))
    refants = [int(r) for r in refants]
    two_pi_eps = 2 * math.pi * eps
    # ---- the solve units: one per (correlation, scan), or both hands of a scan together
    pair = parallel_hand_pair(corr_names, antenna_corrs) if hands is not None else None
    tie = {}      # (scan, antenna, seg in the second hand) -> (seg in the first, j)
    if pair is not None:
        for (s, p, a, b), (j, _) in hand_ties(hands["phase"], hands["segment"],
                                               hands["scan_of_time"], *pair).items():
            tie[(s, p, b)] = (a, j)
    tied_scans = {key[0] for key in tie}
    units = []
    done = set()
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

    def build(unit):
        """Nodes (c, p, seg), their solve group and offset, and the unit's edges."""
        nodes, edges = {}, []
        s = unit[0][1]
        for c, _ in unit:
            for b, key, zz, nn in groups[(c, s)]:
                seg = key % segment_key
                va = nodes.setdefault((c, int(ant1[b]), seg // PAIR_KEY), len(nodes))
                vb = nodes.setdefault((c, int(ant2[b]), seg % PAIR_KEY), len(nodes))
                edges.append((c, s, b, key, va, vb, complex(zz), nn))
        group = np.full(len(nodes), -1, np.int64)
        offset = np.zeros(len(nodes), np.int64)
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
        return nodes, group, offset, edges

    built = [build(u) for u in units]
    # ---- the hands' antenna-based phase difference, over the whole track
    n_ant = len(antenna_names)
    rot = np.ones(n_ant, np.complex128)
    if pair is not None and any(len(u) == 2 for u in units):
        h = np.zeros((n_ant, n_ant), np.complex128)
        for unit, (nodes, group, offset, edges) in zip(units, built):
            if len(unit) != 2:
                continue
            first = {}
            for c, s, b, key, va, vb, zz, nn in edges:
                if c == pair[0]:
                    first[(b, group[va], group[vb])] = zz
            for c, s, b, key, va, vb, zz, nn in edges:
                z1 = first.get((b, group[va], group[vb])) if c == pair[1] else None
                if z1 is None:
                    continue
                z2 = zz * np.exp(-1j * two_pi_eps * (offset[va] - offset[vb]))
                p, q = int(ant1[b]), int(ant2[b])
                h[p, q] += z1 * np.conj(z2)
                h[q, p] += np.conj(z1) * z2
        rot = _phase_sync(h)
    segment_k, antennas, solves, series = {}, [], [], []
    for unit, (nodes, group, offset, edges) in zip(units, built):
        n_groups = int(group.max()) + 1 if group.size else 0
        ga = np.array([group[e[4]] for e in edges], np.int64)
        gb = np.array([group[e[5]] for e in edges], np.int64)
        zrot = np.array([e[6] * np.exp(-1j * two_pi_eps * (offset[e[4]] - offset[e[5]]))
                         * ((rot[int(ant1[e[2]])] * np.conj(rot[int(ant2[e[2]])]))
                            if len(unit) == 2 and e[0] == pair[1] else 1.0)
                         for e in edges], np.complex128)
        n = np.array([e[7] for e in edges], np.int64)
        names = sorted(nodes, key=nodes.get)          # (c, p, seg) per node
        gauge_order = []
        for r in refants:
            for (c, p, sp) in sorted(nodes):
                if p == r and int(group[nodes[(c, p, sp)]]) not in gauge_order:
                    gauge_order.append(int(group[nodes[(c, p, sp)]]))
        sol = solve_lattice(n_groups, ga, gb, zrot, n, eps, max_k, gauge_order=gauge_order)
        k_node = np.array([_canonical_k(int(sol.k[group[v]] + offset[v]), eps, max_k)
                           for v in range(len(names))], np.int64)
        node_ph = np.exp(1j * two_pi_eps * k_node)
        s = unit[0][1]
        hands_label = "+".join(corr_names[c] for c, _ in unit)
        for i, (c, _, b, key, va, vb, zz, nn) in enumerate(edges):
            d = int(k_node[va] - k_node[vb])
            segment_k[(b, c, key)] = d
            after = zz * np.conj(node_ph[va]) * node_ph[vb]
            series.append({"baseline": baseline_names[b], "correlation": corr_names[c],
                           "scan": int(scans[s]), "segment": int(key % segment_key),
                           "solve": "antenna", "k": d,
                           "residual_deg": (math.degrees(abs(math.atan2(after.imag, after.real)))
                                            if nn else None),
                           "coherence": float(abs(after) / nn) if nn else 0.0,
                           "samples": int(nn)})
        gauges = set(int(g) for g in sol.gauge)
        for v, (c, p, seg) in enumerate(names):
            g = int(group[v])
            # the group's sum over both hands, in this node's frame
            w = complex(sol.node_sum[g]) * np.exp(1j * two_pi_eps * offset[v])
            choice = choose_offset(w, int(sol.node_count[g]), eps, max_k, ambiguity_deg,
                                   k=int(k_node[v]))
            entry = {"antenna": antenna_names[p], "correlation": corr_names[c],
                     "scan": int(scans[s]), "segment": int(seg), "reference": g in gauges,
                     # indices, for the gains of a calibration table (hitops/calibrate/gains.py)
                     "antenna_index": int(p), "correlation_index": int(c), "scan_index": int(s),
                     "baselines": int(sum(1 for e in edges if v in (e[4], e[5])))}
            if len(unit) == 2:
                entry["hands"] = hands_label
                entry["tied"] = bool(np.sum(group == g) > 1)
            if choice is None:
                entry.update(k=int(k_node[v]), samples=0, note="no sample to compare")
            else:
                entry.update(choice.as_dict())
                entry["margin_deg"] = (None if choice.runner_up_residual_deg is None else
                                       choice.runner_up_residual_deg - choice.residual_deg)
            antennas.append(entry)
        for comp, g0 in enumerate(sol.gauge):
            idx = [i for i in range(len(edges)) if sol.component[ga[i]] == comp]
            members = [v for v in range(len(names)) if sol.component[group[v]] == comp]
            ref_node = next((v for v in members if group[v] == g0), members[0] if members else 0)
            for c, _ in unit:
                cidx = [i for i in idx if edges[i][0] == c]
                samples = int(sum(n[i] for i in cidx))
                after = [edges[i][6] * np.conj(node_ph[edges[i][4]]) * node_ph[edges[i][5]]
                         for i in cidx]
                mism = np.array([math.degrees(math.atan2(a.imag, a.real)) for a in after])
                worst = int(np.argmax(np.abs(mism))) if cidx else None
                solves.append({
                    "correlation": corr_names[c], "scan": int(scans[s]),
                    "reference": f"{antenna_names[names[ref_node][1]]}/{names[ref_node][2]}",
                    "antenna_segments": sum(1 for v in members if names[v][0] == c),
                    "baselines": len(cidx), "samples": samples,
                    "method": sol.method, "hands": hands_label,
                    "coherence": (float(sum(a.real for a in after) / samples) if samples else 0.0),
                    "residual_rms_deg": float(np.sqrt(np.mean(mism ** 2))) if cidx else None,
                    "worst_baseline": baseline_names[edges[cidx[worst]][2]] if cidx else None,
                    "worst_residual_deg": float(abs(mism[worst])) if cidx else None})
    return segment_k, antennas, solves, series


def offset_shift_rows(tgt_grid, eps: float, segment_k, seg_keys, phasors) -> bool:
    """Multiply ``phasors`` (PWC/CWU, (n_row, n_corr) each, in place) by exp(i 2 pi eps k).

    ``segment_k``: {(b, c, key): k} added to the wrap counts of a segment by the n0 step
    (robust trackers), which moves its PWC and CWU output by 2 pi eps k; ``seg_keys``
    (n_bl, n_corr, n_time) the chunk's segment keys; ``tgt_grid`` (n_bl, n_time) the
    chunk's target rows.  Used to shift the first pass's output instead of running the
    transfer again (one chunk); equal to the second pass to complex64 rounding.
    Returns whether anything moved.
    """
    from .lattice import shift_rows
    from ..tracking.state import apply_segment_offsets

    if seg_keys is None or not any(segment_k.values() if segment_k else ()):
        return False
    k = apply_segment_offsets(np.zeros(seg_keys.shape, np.int64), seg_keys, segment_k)
    values = [v for v in segment_k.values()]
    k_min, k_max = min(values + [0]), max(values + [0])
    table = np.exp(1j * (2 * math.pi * eps) * np.arange(k_min, k_max + 1)).astype(np.complex64)
    grid = np.ascontiguousarray(tgt_grid)
    for out in phasors:
        shift_rows(grid, k, table, k_min, out)
    return True
