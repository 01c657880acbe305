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
    else:
        best = int(np.flatnonzero(ks == int(k))[0])
    distinct = np.abs(np.array([_wrap(o - offsets[best]) for o in offsets])) > 1e-9
    runner_k = runner_res = None
    ambiguous = False
    if np.any(distinct):
        idx = np.flatnonzero(distinct)
        # the smallest |k| among runner-ups equal to rounding (k and k + 43 for 29/43)
        j = int(idx[np.flatnonzero(residuals[idx] <= residuals[idx].min() + 1e-9)[0]])
        runner_k = int(ks[j])
        runner_res = math.degrees(residuals[j])
        ambiguous = (runner_res - math.degrees(residuals[best])) < ambiguity_deg
    return OffsetChoice(k=int(ks[best]), offset_deg=math.degrees(offsets[best]),
                        measured_deg=math.degrees(measured),
                        residual_deg=math.degrees(residuals[best]), runner_up_k=runner_k,
                        runner_up_residual_deg=runner_res,
                        coherence=float(abs(z_sum) / count), samples=int(count),
                        ambiguous=bool(ambiguous))


# ----------------------------------------------------------------------------- the model

#: ``--offset-model point``: a point source at the phase centre (model phase 0 everywhere)
POINT_MODEL = "point"
#: antenna mode: a baseline's segment id is sp * PAIR_KEY + sq, sp and sq the aligned
#: segment ids of its two antennas (hitops.calibrate.robust.ReferenceTracker.track)
PAIR_KEY = 1_000_003


def is_point_model(offset_model) -> bool:
    return bool(offset_model) and str(offset_model).strip().lower() == POINT_MODEL


def antenna_offsets(seg_sums, antenna_corrs, ant1, ant2, antenna_names, baseline_names,
                    corr_names, scans, eps: float, max_k: int, ambiguity_deg: float,
                    refants=(), segment_key: int = 1 << 32):
    """The n0 step of the antenna tracker: integers per antenna and segment on the lattice.

    ``seg_sums``: {(baseline, correlation, key): (z, n)} with z the sum of
    exp(i (Phi_model - Phi_out)) over the samples of that baseline segment
    (:func:`hitops.calibrate.robust.segment_offset_sums`), key = scan index *
    ``segment_key`` + sp * PAIR_KEY + sq for the correlations in ``antenna_corrs``.
    Per (correlation, scan) the antenna segments are the nodes and the baseline
    segments the edges of one :func:`hitops.calibrate.lattice.solve_lattice`; the
    reference antenna's segment (first of ``refants`` present, else the node with
    most samples) is the gauge, k = 0.

    Returns (segment_k, antennas, solves, series): segment_k {(b, c, key): k_p - k_q}
    to add to the baseline wrap counts; one report entry per antenna segment (k,
    measured offset, residual, runner-up, margin, coherence, samples, reference,
    ambiguous), one per solve (component), and one per baseline segment (its k and
    the mismatch left).
    """
    from .lattice import solve_lattice

    groups = {}
    for (b, c, key), (z, n) in seg_sums.items():
        if c not in antenna_corrs:
            continue
        groups.setdefault((int(c), int(key // segment_key)), []).append((int(b), int(key), z, int(n)))
    segment_k, antennas, solves, series = {}, [], [], []
    refants = [int(r) for r in refants]
    for (c, s), edges in sorted(groups.items()):
        nodes = {}

        def node(p, seg):
            return nodes.setdefault((p, seg), len(nodes))

        ea, eb, z, n = [], [], [], []
        for b, key, zz, nn in edges:
            seg = key % segment_key
            ea.append(node(int(ant1[b]), seg // PAIR_KEY))
            eb.append(node(int(ant2[b]), seg % PAIR_KEY))
            z.append(complex(zz))
            n.append(nn)
        names = sorted(nodes, key=nodes.get)
        gauge_order = [nodes[ps] for r in refants for ps in sorted(nodes) if ps[0] == r]
        sol = solve_lattice(len(nodes), ea, eb, z, n, eps, max_k, gauge_order=gauge_order)
        for (b, key, _, nn), i in zip(edges, range(len(edges))):
            d = int(sol.k[ea[i]] - sol.k[eb[i]])
            segment_k[(b, c, key)] = d
            after = sol.edge_sum[i]
            series.append({"baseline": baseline_names[b], "correlation": corr_names[c],
                           "scan": int(scans[s]), "segment": int(key % segment_key),
                           "solve": "antenna", "k": d,
                           "residual_deg": (math.degrees(abs(math.atan2(after.imag, after.real)))
                                            if nn else None),
                           "coherence": float(abs(after) / nn) if nn else 0.0,
                           "samples": int(nn)})
        gauges = set(int(g) for g in sol.gauge)
        for v, (p, seg) in enumerate(names):
            is_ref = v in gauges
            choice = choose_offset(complex(sol.node_sum[v]), int(sol.node_count[v]), eps,
                                   max_k, ambiguity_deg, k=int(sol.k[v]))
            entry = {"antenna": antenna_names[p], "correlation": corr_names[c],
                     "scan": int(scans[s]), "segment": int(seg), "reference": is_ref,
                     # indices, for the gains of a calibration table (hitops/calibrate/gains.py)
                     "antenna_index": int(p), "correlation_index": int(c), "scan_index": int(s),
                     "baselines": int(sum(1 for i in range(len(ea)) if v in (ea[i], eb[i])))}
            if choice is None:
                entry.update(k=int(sol.k[v]), samples=0, note="no sample to compare")
            else:
                entry.update(choice.as_dict())
                entry["margin_deg"] = (None if choice.runner_up_residual_deg is None else
                                       choice.runner_up_residual_deg - choice.residual_deg)
            antennas.append(entry)
        for comp, g in enumerate(sol.gauge):
            members = [v for v in range(len(names)) if sol.component[v] == comp]
            idx = [i for i in range(len(ea)) if sol.component[ea[i]] == comp]
            samples = int(sum(n[i] for i in idx))
            mism = np.array([math.degrees(math.atan2(sol.edge_sum[i].imag, sol.edge_sum[i].real))
                             for i in idx])
            worst = int(np.argmax(np.abs(mism))) if idx else None
            solves.append({
                "correlation": corr_names[c], "scan": int(scans[s]),
                "reference": f"{antenna_names[names[int(g)][0]]}/{names[int(g)][1]}",
                "antenna_segments": len(members), "baselines": len(idx), "samples": samples,
                "method": sol.method,
                "coherence": (float(sum(sol.edge_sum[i].real for i in idx) / samples)
                              if samples else 0.0),
                "residual_rms_deg": float(np.sqrt(np.mean(mism ** 2))) if idx else None,
                "worst_baseline": baseline_names[edges[idx[worst]][0]] if idx else None,
                "worst_residual_deg": float(abs(mism[worst])) if idx else None})
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
    from .robust import apply_segment_offsets

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
