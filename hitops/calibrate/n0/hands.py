"""The two parallel hands of the antenna n0 step: which hands, and how their integers relate.

Both parallel hands (RR and LL, or XX and YY) see the same troposphere, so the
reference band's tracked antenna phases tie one hand's wrap-count errors to the
other's (:func:`hand_ties`), and the product of the two hands' baseline sums
gives their antenna-based instrumental phase difference (:func:`phase_sync`).
:mod:`hitops.calibrate.n0.antenna` uses both to solve the hands together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class HandPhases:
    """The reference band's tracked antenna phases (the antenna tracker's first pass).

    ``phase`` (n_ant, n_corr, n_time) float64 unwrapped antenna phases, NaN where
    unsolved; ``segment`` (n_ant, n_corr, n_time) int64 aligned segment ids, -1 for
    none; ``scan_of_time`` (n_time,) tracking-scan index of each time.
    """

    phase: np.ndarray
    segment: np.ndarray
    scan_of_time: np.ndarray


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
    per antenna, which the hand rotation of :func:`hitops.calibrate.n0.antenna.antenna_offsets` absorbs.

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


def phase_sync(h) -> np.ndarray:
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
