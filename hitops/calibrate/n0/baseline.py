"""The per-baseline n0 offset of PWC (paper, Results and discussion, eq. Delta_pwc).

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


def canonical_k(k: int, eps: float, max_k: int) -> int:
    """The smallest |k'| <= max_k with 2 pi eps k' = 2 pi eps k (mod 2 pi); k if none."""
    m = 0
    while m <= max_k:
        for kk in ((0,) if m == 0 else (-m, m)):
            if abs(_wrap(2 * math.pi * eps * (kk - k))) < 1e-9:
                return kk
        m += 1
    return int(k)



def channel_candidates(max_k: int) -> np.ndarray:
    """|k| <= max_k, smallest |k| first (0, -1, 1, ...): ties go to the smallest |k|."""
    ks = np.arange(-int(max_k), int(max_k) + 1, dtype=np.int64)
    return ks[np.argsort(np.abs(ks), kind="stable")]


@dataclass(frozen=True)
class WindowRatios:
    """A target window's ratios for the n0 step across its channels: ``ratios`` (n_chan,)
    R_j = nu_j / nu_ref, ``centre`` R_0 at the window centre nu_0 (where the output's
    phasor refers), ``eps`` R_0's fractional part (the group's eps)."""

    ratios: np.ndarray
    centre: float
    eps: float

    def turns(self, k) -> np.ndarray:
        """exp(2*pi*i*R_j*k) per channel (k scalar: (n_chan,); k (n,): (n, n_chan)), from the
        fractional turns of R_j*k only (exact for |k| up to ~1e6)."""
        t = np.multiply.outer(np.asarray(k, np.float64), self.ratios)
        return np.exp(2j * math.pi * (t - np.floor(t)))


def choose_channel_offset(z_chan, count: int, window: WindowRatios, max_k: int,
                          ambiguity_deg: float, k: int | None = None) -> OffsetChoice | None:
    """:func:`choose_offset` over a window's channels: k in [-max_k, max_k] maximising
    Re(sum_j z_j exp(-2*pi*i*R_j*k)) (:func:`hitops.kernels.wideband.channel_offset_scores`).

    ``z_chan`` (n_chan,) the per-channel sums, ``count`` their samples over all channels.
    A score s reads as the residual arccos(s) (one channel: |measured - offset|, as
    :func:`choose_offset`); ``measured_deg`` is the offset at the window centre (the sums
    with the chosen k's slope across the window taken out), ``offset_deg`` 2*pi*eps*k.
    ``ambiguous``: the runner-up (any other k: across channels k and k + 43 differ) within
    ``ambiguity_deg`` of the best.  ``k``: describe that candidate instead of choosing.
    None when there are no samples.
    """
    from ...kernels.wideband import channel_offset_scores

    z_chan = np.asarray(z_chan, np.complex128)
    if count <= 0 or not np.any(z_chan != 0):
        return None
    ks = channel_candidates(max_k)
    if k is not None and int(k) not in ks:
        ks = np.append(ks, np.int64(k))
    scores = channel_offset_scores(z_chan, window.ratios, ks)
    residual = np.degrees(np.arccos(np.clip(scores, -1.0, 1.0)))
    best = int(np.argmax(scores)) if k is None else int(np.flatnonzero(ks == int(k))[0])
    others = np.flatnonzero(np.arange(ks.size) != best)
    runner = int(others[np.argmax(scores[others])]) if others.size else None
    best_k = int(ks[best])
    slope = (window.ratios - window.centre) * best_k
    aligned = complex(np.sum(z_chan * np.exp(-2j * math.pi * (slope - np.floor(slope)))))
    return OffsetChoice(
        k=best_k, offset_deg=math.degrees(_wrap(2 * math.pi * window.eps * best_k)),
        measured_deg=math.degrees(math.atan2(aligned.imag, aligned.real)),
        residual_deg=float(residual[best]),
        runner_up_k=None if runner is None else int(ks[runner]),
        runner_up_residual_deg=None if runner is None else float(residual[runner]),
        coherence=float(abs(aligned) / count), samples=int(count),
        ambiguous=bool(runner is not None and residual[runner] - residual[best] < ambiguity_deg))
