"""Will FPT help?  A prediction per baseline, and a check of the reference band's closures.

FPT replaces the target band's phase fluctuation by R times the reference band's
(the paper's sigma_FPT^2 = sigma_t^2 + R^2 sigma_r^2 for the thermal part): it pays
where the target's fluctuation that the reference band shares (the troposphere)
costs more coherence than the reference noise it brings.  On raw data it gains;
on data already fringe fitted per band, as the EHT's public releases are, the
bands' residual fluctuations are independent and it loses.

Per baseline and parallel hand, at the interval T (diagnose's default 60 s), from
phase increments at lags tau within scans and sampled blocks (samples matched in
time):

* structure functions D = -2 ln |<exp(i increment)>| (the variance of Gaussian
  increments, blind to 2 pi) of the target phase Phi, of R phi (phi unwrapped from
  sample to sample, as PWC counts it) and of their difference Phi - R phi: the
  difference is what FPT leaves, the troposphere the bands share cancels in it,
  the reference's own noise (2 R^2 sigma_r^2) and fluctuation stay;
* within-window phase variance V = sum_tau (N - tau) D(tau) / N^2 (N = T / dt): V_t
  before FPT, V_d after; V_t + V_r - V_d is the part the bands share (2 V_x);
* with C ~ exp(-V / 2) (Gaussian phases) and the noise bias of a mean of N samples,
  sqrt(C^2 + (1 - C^2) / N), which C(T) carries too, the predicted change of C(T)
  is the ratio after / before, minus 1;
* reported beside it: the reference's thermal noise per sample sigma_r (scatter of
  consecutive amplitudes, which the troposphere barely moves, over the median
  amplitude; the SIGMA column's value beside it, as conventions differ: the EHT
  releases' RR/LL errors are sqrt(2) times those of Stokes I).

"help" above +1%, "hurt" below -1%, "neutral" between.  Wrap errors (the trackers'
job) and source structure (see the closure check) are not in it.

Closure check: the reference band's closure phases averaged per triangle; when the
median triangle's mean closure is more than 3 of its standard errors and more than
1 degree from zero, the source has structure at the reference band, and a
baseline-based transfer writes R times it into the target.

Both come from blocks of times spread over the track, not the whole track
(:mod:`hitops.calibrate.verdict_sample`); the log gets one summary line, the
report the table per baseline.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ..errors import MeasurementSetError
from .verdict_sample import quiet_nanmedian

log = logging.getLogger("hitops.calibrate")

#: predicted or measured changes within +-this fraction count as neutral
NEUTRAL = 0.01
#: sample pairs per lag and series for a structure function (relative error ~1/sqrt(2 x this))
MAX_PAIRS = 2000
#: the reference closures show structure only beyond this many standard errors ...
CLOSURE_SIGNIFICANCE = 3.0
#: ... and this many degrees (median triangle's |mean closure|): float32 rounding of
#: noise-free data is ~1e-5 deg, and R x 1 deg (2.7 deg at 230/86 GHz) is below what a
#: mm-VLBI closure phase is usually known to
CLOSURE_FLOOR_DEG = 1.0


@dataclass
class BaselineVerdict:
    baseline: str
    correlation: str
    sigma_target_rad: float      # thermal phase noise per sample, target band
    sigma_ref_rad: float         # thermal phase noise per sample, reference band
    sigma_ratio_target: float    # measured scatter / SIGMA column (NaN without SIGMA)
    sigma_ratio_ref: float
    window_var_target: float     # V_t (rad^2): the target's phase variance within T
    window_var_shared: float     # V_t + V_r - V_d (2 V_x for Gaussian phases): what FPT removes
    window_var_ref: float        # V_r: what FPT brings (R^2 x the reference's)
    predicted_change: float      # predicted C(T) after / before - 1
    verdict: str                 # help | hurt | neutral
    measured_change: float = float("nan")   # filled in by measure()

    def as_dict(self) -> Dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in self.__dict__.items()}


@dataclass
class Verdict:
    interval: float
    ratio: float
    baselines: List[BaselineVerdict] = field(default_factory=list)
    closure: Optional[Dict] = None
    sampled: Optional[Dict] = None     # times read of the track (verdict_sample.TimeBlocks)

    def as_dict(self) -> Dict:
        return {"interval_s": self.interval, "ratio": self.ratio,
                "baselines": [b.as_dict() for b in self.baselines],
                "reference_closure": self.closure, "sampled": self.sampled}


def _word(change: float) -> str:
    if not math.isfinite(change):
        return "unknown"
    return "help" if change > NEUTRAL else "hurt" if change < -NEUTRAL else "neutral"


def expected_mean_length(c, n: float):
    """E|mean of n unit phasors| whose coherence is c: sqrt(c^2 + (1 - c^2) / n).

    C(T) of n noisy samples is biased up by the noise; the same bias is applied to
    the prediction so that both speak of the same quantity.
    """
    c = np.asarray(c, dtype=np.float64)
    return np.sqrt(c ** 2 + (1.0 - c ** 2) / max(float(n), 1.0))


def thermal_phase_noise(vis: np.ndarray, flag: np.ndarray, segment: np.ndarray):
    """(sigma_phase, amplitude, sigma_component) per (baseline, correlation) of a grid.

    vis, flag (n_bl, n_time, n_corr); segment (n_bl, n_time): equal values mark
    consecutive times (one scan, one sampled block).  Consecutive valid samples of
    one segment give amplitude differences whose robust spread is sqrt(2) s.  A
    series without two consecutive valid samples gives NaN (reported as unknown).
    """
    amp = np.abs(vis).astype(np.float64)
    ok = ~flag & (amp > 0) & np.isfinite(amp)
    same = (segment[:, 1:] == segment[:, :-1])[:, :, None]
    pair = ok[:, 1:] & ok[:, :-1] & same
    diff = np.where(pair, amp[:, 1:] - amp[:, :-1], np.nan)
    with np.errstate(all="ignore"):
        mad = quiet_nanmedian(np.abs(diff - quiet_nanmedian(diff, axis=1, keepdims=True)), axis=1)
        s = 1.4826 * mad / math.sqrt(2.0)
        a = quiet_nanmedian(np.where(ok, amp, np.nan), axis=1)
        return s / a, a, s


def closure_check(grid, sigma_phase: np.ndarray, max_triangles: int = 200) -> Optional[Dict]:
    """Mean reference closure phase per triangle against its standard error (first hand).

    ``grid``: a :class:`hitops.calibrate.verdict_sample.SampledBand`.  The median
    triangle's mean closure counts as structure only when it is both more than
    :data:`CLOSURE_SIGNIFICANCE` standard errors and more than
    :data:`CLOSURE_FLOOR_DEG` degrees from zero: noise-free data have a standard
    error of zero, and rounding alone would be "significant".
    """
    from ..tracking.antenna_kernel import closure_phases

    ants = sorted(set(grid.ant1.tolist()) | set(grid.ant2.tolist()))
    if len(ants) < 3:
        return None
    triangles = np.array([(p, q, r) for i, p in enumerate(ants) for j, q in enumerate(ants[i + 1:], i + 1)
                          for r in ants[j + 1:]], dtype=np.int64)[:max_triangles]
    c = 0
    vis = grid.vis[:, :, c]
    valid = ~grid.flag[:, :, c] & (np.abs(vis) > 0)
    phase = np.where(valid, np.angle(vis.astype(np.complex128)), 0.0)
    closures = closure_phases(np.ascontiguousarray(phase), np.ascontiguousarray(valid),
                              grid.ant1.astype(np.int64), grid.ant2.astype(np.int64), triangles)
    stats = []
    bl_of = {(int(p), int(q)): b for b, (p, q) in enumerate(zip(grid.ant1, grid.ant2))}
    for k, (p, q, r) in enumerate(triangles):
        cl = closures[k][np.isfinite(closures[k])]
        if cl.size < 3:
            continue
        legs = [bl_of.get((p, q), bl_of.get((q, p))), bl_of.get((q, r), bl_of.get((r, q))),
                bl_of.get((p, r), bl_of.get((r, p)))]
        sig = math.sqrt(sum(float(sigma_phase[b, c]) ** 2 for b in legs if b is not None))
        mean = np.mean(np.exp(1j * cl))
        error = max(sig / math.sqrt(cl.size), 1e-12)
        stats.append((abs(float(np.angle(mean))), abs(float(np.angle(mean))) / error))
    if not stats:
        return None
    values = np.array(stats)
    median_deg = float(np.degrees(np.median(values[:, 0])))
    significance = float(np.median(values[:, 1]))
    return {"triangles": int(values.shape[0]),
            "median_abs_mean_closure_deg": median_deg,
            "median_significance": significance,
            "floor_deg": CLOSURE_FLOOR_DEG,
            "consistent_with_zero": bool(significance <= CLOSURE_SIGNIFICANCE
                                         or median_deg <= CLOSURE_FLOOR_DEG)}


def _aligned(tgt_times: np.ndarray, ref_times: np.ndarray, tolerance: float):
    """Index into ref_times of each target time (-1 where no reference time is that close)."""
    pos = np.clip(np.searchsorted(ref_times, tgt_times), 1, max(ref_times.size - 1, 1))
    lo = np.clip(pos - 1, 0, ref_times.size - 1)
    hi = np.clip(pos, 0, ref_times.size - 1)
    near = np.where(np.abs(ref_times[lo] - tgt_times) <= np.abs(ref_times[hi] - tgt_times), lo, hi)
    return np.where(np.abs(ref_times[near] - tgt_times) <= tolerance, near, -1)


def _unwrap_runs(phase: np.ndarray, valid: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Phase unwrapped along the valid samples of each segment (NaN elsewhere): wraps
    counted from one valid sample to the next, as PWC counts them (np.unwrap's rule,
    restarted at each segment)."""
    out = np.full(phase.shape, np.nan)
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return out
    p = phase[idx]
    step = np.diff(p)
    wrapped = np.mod(step + np.pi, 2 * np.pi) - np.pi
    wrapped[(wrapped == -np.pi) & (step > 0)] = np.pi
    correction = np.where(np.abs(step) < np.pi, 0.0, wrapped - step)
    new_run = np.diff(segment[idx]) != 0
    correction[new_run] = 0.0
    total = np.concatenate([[0.0], np.cumsum(correction)])
    starts = np.concatenate([[0], np.flatnonzero(new_run) + 1])
    out[idx] = p + total - total[starts][np.cumsum(np.concatenate([[0], new_run]))]
    return out


def _structures(phasors: np.ndarray, starts: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """D = -2 ln |<exp(i d)>| of each run of increment phasors exp(i d) (columns
    ``starts`` of length ``sizes``) of each row: the variance of Gaussian increments d,
    blind to 2 pi."""
    means = np.add.reduceat(phasors, starts, axis=1) / sizes
    return -2.0 * np.log(np.maximum(np.abs(means), 1e-12))


def window_variances(phi_t, phi_r, valid, segment, n_window: int, ratio: float):
    """(V_t, V_r, V_d) within windows of n_window samples: of the target phase, of R times
    the reference phase, and of their difference (what FPT leaves).

    phi_t, phi_r (n_time,) wrapped phases on common samples, valid (n_time,), segment
    (n_time,): equal values mark a stretch of consecutive times (a scan, or a scan's
    part in one sampled block).  Structure functions come from increments at lags tau
    within a segment (the reference unwrapped from sample to sample, since R times it
    is what FPT transfers), as D = -2 ln |<exp(i increment)>|; lags on a grid of at
    most 16 values, D(tau) interpolated between them.
    """
    n_window = max(int(n_window), 2)
    lags = np.unique(np.round(np.geomspace(1, n_window - 1, 16)).astype(int)) \
        if n_window > 2 else np.array([1])
    ref_unwrapped = ratio * _unwrap_runs(phi_r, valid, segment)
    firsts, used = [], []
    for k, lag in enumerate(lags):
        ok = np.flatnonzero(valid[lag:] & valid[:-lag] & (segment[lag:] == segment[:-lag]))
        if ok.size < 3:
            continue
        if ok.size > MAX_PAIRS:      # a statistic: an even spread of pairs is enough
            ok = ok[np.linspace(0, ok.size - 1, MAX_PAIRS).astype(np.int64)]
        firsts.append(ok)
        used.append(k)
    if not used:
        return float("nan"), float("nan"), float("nan")
    sizes = np.array([f.size for f in firsts])
    first = np.concatenate(firsts)
    second = first + np.repeat(lags[used], sizes)
    # phasors once per sample, increments as products: exp(i (a - b)) = exp(i a) exp(-i b)
    phasor_t = np.exp(1j * np.where(valid, phi_t, 0.0))
    phasor_r = np.exp(1j * np.where(valid, ref_unwrapped, 0.0))
    step_t = phasor_t[second] * np.conj(phasor_t[first])
    step_r = phasor_r[second] * np.conj(phasor_r[first])
    d = _structures(np.stack([step_t, step_r, step_t * np.conj(step_r)]),
                    np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes)
    taus = np.arange(1, n_window)
    weights = (n_window - taus) / n_window ** 2
    return tuple(float(np.sum(weights * np.interp(taus, lags[used], d[i])))
                 for i in range(3))


def predict(ref_ms: str, target_ms: str, ratio: float, ref_column: str = "DATA",
            target_column: str = "DATA", interval: float = 60.0,
            ref_meta=None, tgt_meta=None, target_flags_of: Optional[str] = None) -> Verdict:
    """The prediction per baseline (parallel hands) and the reference closure check, from
    blocks of times spread over the track (:mod:`hitops.calibrate.verdict_sample`).
    ``ref_meta``/``tgt_meta``: the run's SetMetadata of each set (``RunPlan``), read
    again when None; ``target_flags_of``: the output column whose flags a processing
    set's target samples take (:func:`~hitops.calibrate.verdict_sample.read_sampled`)."""
    from .verdict_sample import (choose_blocks, distinct_times, read_sampled, read_times,
                                 sampling_interval)

    tgt_time, ref_time = read_times(target_ms), read_times(ref_ms)
    tgt_times, ref_times = distinct_times(tgt_time), distinct_times(ref_time)
    if tgt_times.size == 0 or ref_times.size == 0:
        raise MeasurementSetError(f"{target_ms if tgt_times.size == 0 else ref_ms}: the main "
                                  "table has no rows")
    dt = {"tgt": sampling_interval(tgt_times), "ref": sampling_interval(ref_times)}
    if not dt["tgt"] > 0:   # one time step: no increment to take, nothing to predict
        return Verdict(interval=float(interval), ratio=float(ratio),
                       sampled={"times_read": 0, "times": int(tgt_times.size), "blocks": 0})
    n_window = int(round(interval / dt["tgt"]))
    blocks = choose_blocks(tgt_times, n_window, MAX_PAIRS)
    tgt = read_sampled(target_ms, target_column, tgt_time, blocks, tgt_meta, target_flags_of)
    ref = read_sampled(ref_ms, ref_column, ref_time, blocks, ref_meta)
    verdict = Verdict(interval=float(interval), ratio=float(ratio), sampled=blocks.as_dict())
    sig_t, _, s_t = thermal_phase_noise(tgt.vis, tgt.flag, tgt.segment)
    sig_r, _, s_r = thermal_phase_noise(ref.vis, ref.flag, ref.segment)
    with np.errstate(all="ignore"):   # SIGMA zero or absent: no ratio
        ratio_t, ratio_r = s_t / tgt.sigma, s_r / ref.sigma
    verdict.closure = closure_check(ref, sig_r)
    at = _aligned(tgt.times, ref.times, 0.5 * min(dt["tgt"], dt["ref"]))
    ref_index = {}
    for b in range(ref.n_bl):
        p, q = ref.antenna_names[ref.ant1[b]], ref.antenna_names[ref.ant2[b]]
        ref_index[(p, q)] = (b, 1.0)
        ref_index[(q, p)] = (b, -1.0)     # reversed baseline: phases change sign
    for b in range(tgt.n_bl):
        p, q = tgt.antenna_names[tgt.ant1[b]], tgt.antenna_names[tgt.ant2[b]]
        if (p, q) not in ref_index:
            continue
        rb, sign = ref_index[(p, q)]
        for c, corr in enumerate(tgt.corr_names):
            if corr not in ref.corr_names:
                continue
            rc = ref.corr_names.index(corr)
            vis_t = tgt.vis[b, :, c]
            vis_r = np.where(at >= 0, ref.vis[rb, np.maximum(at, 0), rc], 0)
            valid = (~tgt.flag[b, :, c] & (at >= 0) & ~ref.flag[rb, np.maximum(at, 0), rc]
                     & (np.abs(vis_t) > 0) & (np.abs(vis_r) > 0))
            if valid.sum() < 3:
                continue
            v_t, v_r, v_d = window_variances(np.angle(vis_t.astype(np.complex128)),
                                             sign * np.angle(vis_r.astype(np.complex128)),
                                             valid, tgt.segment[b], n_window, ratio)
            change = (float(expected_mean_length(math.exp(-v_d / 2), n_window)
                            / expected_mean_length(math.exp(-v_t / 2), n_window)) - 1
                      if math.isfinite(v_r) else float("nan"))
            verdict.baselines.append(BaselineVerdict(
                baseline=tgt.baseline_name(b), correlation=corr,
                sigma_target_rad=float(sig_t[b, c]), sigma_ref_rad=float(sig_r[rb, rc]),
                sigma_ratio_target=float(ratio_t[b, c]), sigma_ratio_ref=float(ratio_r[rb, rc]),
                window_var_target=v_t, window_var_shared=v_t + v_r - v_d, window_var_ref=v_r,
                predicted_change=change, verdict=_word(change)))
    return verdict


def measure(verdict: Verdict, target_ms: str, target_column: str, output_column: str) -> None:
    """Fill in the measured change of C(T) from ``target_column`` to ``output_column``."""
    from ..diagnose.metrics import compute_coherence
    from ..diagnose.read import read_grid

    grid = read_grid(target_ms, [target_column, output_column])
    coh = compute_coherence(grid.vis_stack, [target_column, output_column], grid.flag, grid.times,
                            grid.scan, grid.dt, np.array([verdict.interval]), verdict.interval)
    k = coh.k_interval
    before, after = coh.c_mean[target_column][:, :, k], coh.c_mean[output_column][:, :, k]
    index = {(grid.baseline_name(b), corr): (b, c) for b in range(grid.n_bl)
             for c, corr in enumerate(grid.corr_names)}
    for entry in verdict.baselines:
        where = index.get((entry.baseline, entry.correlation))
        if where is not None:
            entry.measured_change = float(after[where] / before[where] - 1.0)


def summary(verdict: Verdict) -> Dict:
    """Counts of the verdicts, and how often the predicted sign matched the measured one."""
    entries = verdict.baselines
    judged = [e for e in entries if math.isfinite(e.measured_change)]
    agree = [e for e in judged if _word(e.measured_change) == e.verdict]
    sign = [e for e in judged if np.sign(e.measured_change) == np.sign(e.predicted_change)]
    errors = np.array([e.predicted_change - e.measured_change for e in judged])
    return {"help": sum(e.verdict == "help" for e in entries),
            "hurt": sum(e.verdict == "hurt" for e in entries),
            "neutral": sum(e.verdict == "neutral" for e in entries),
            "measured": len(judged), "verdict_agrees": len(agree), "sign_agrees": len(sign),
            "median_abs_error": float(np.median(np.abs(errors))) if errors.size else None}


def log_verdict(verdict: Verdict, methods_transfer_baselines: bool, has_model: bool,
                report_path: str = "the JSON report") -> None:
    """One summary line (the per-baseline table is in the report), and the closure warning
    if due."""
    s = summary(verdict)
    known = [e for e in verdict.baselines if math.isfinite(e.predicted_change)]
    spread = ""
    if known:
        low = min(known, key=lambda e: e.predicted_change)
        high = max(known, key=lambda e: e.predicted_change)
        spread = (f"; predicted change of C({verdict.interval:.0f} s) from "
                  f"{100 * low.predicted_change:+.1f}% ({low.baseline} {low.correlation}) to "
                  f"{100 * high.predicted_change:+.1f}% ({high.baseline} {high.correlation})")
    sampled = verdict.sampled or {}
    basis = (f", from {sampled['times_read']} of {sampled['times']} times"
             if sampled and sampled["times_read"] < sampled["times"] else "")
    log.info("verdict%s: FPT expected to help on %d, hurt on %d, be neutral on %d baseline x "
             "correlation series%s%s; per baseline in %s (verdict)", basis, s["help"], s["hurt"],
             s["neutral"], spread,
             (f"; measured after the run: the verdict matches on {s['verdict_agrees']} of "
              f"{s['measured']}, the sign on {s['sign_agrees']}" if s["measured"] else ""),
             report_path)
    cl = verdict.closure
    if cl and not cl["consistent_with_zero"] and methods_transfer_baselines and not has_model:
        log.warning("the reference band's closure phases are not consistent with zero (median "
                    "|mean closure| %.1f deg, %.1f standard errors, %d triangles): the source has "
                    "structure there, and a baseline-based transfer writes R times it into the "
                    "target; use --tracker antenna (keeps the target's closure phases) or give "
                    "--ref-model-column", cl["median_abs_mean_closure_deg"],
                    cl["median_significance"], cl["triangles"])
