"""The reference wrap count carried across scan and field switches, for the calibrator step.

The count tracker restarts its count at every scan, so PWC leaves each scan of each
baseline with its own constant: the transfer used psi_s = phi + 2 pi n'(t) with n'
from 0 at the scan's first sample, while the count continued over the whole track
(both fields) gives psi_c = psi_s + 2 pi N_s, N_s the continued count at that first
sample.  Channel k's output thus carries exp(+i 2 pi R_k N_s): a phase and a delay
N_s / nu_ref that differ from scan to scan, the calibrator's scans included, and no
interpolation between calibrator scans can remove them.  Multiplying every scan by
exp(-i 2 pi R_k N_s) leaves one constant per baseline for the whole track instead
(2 pi eps n0 of the track's first sample), the same on every field.

Counting across a switch needs the reference phase to be continuous through it: the
same troposphere and instrument on both lines of sight (a nearby calibrator, a slew
shorter than the reference band's coherence time) and point sources at both phase
centres (or --ref-model-column).  The largest step met at a scan's first sample is
reported: near 180 degrees the count across that switch is a guess.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np

from ...io.match import correlation_map, parse_antenna_map
from ...io.stations import stations_of
from ..channels import reduce_rows
from ..set_rows import open_set_rows, reference_sources

#: a step at a scan's first sample beyond this (deg) is counted as a risky switch
RISKY_STEP_DEG = 90.0
#: samples on each side of a gap whose rate carries the phase across it
RATE_SAMPLES = 5


@dataclass(frozen=True)
class SwitchCounts:
    """The continued count N at the scan start of every target row given, per correlation."""

    counts: np.ndarray           # (n_row, n_corr) int64
    n_scan_starts: int           # series x scans bridged
    largest_step_deg: float      # the largest |step residual| at a scan's first sample
    n_risky: int                 # scan starts with a step beyond RISKY_STEP_DEG


def _reference_series(run, groups, ref_rows: np.ndarray) -> Tuple[Dict, np.ndarray, np.ndarray]:
    """The reference set's rows of the groups' window: columns and (n_row, n_corr) phase
    (the channels reduced to one phase as the transfer does) and its validity, read in
    blocks of the run's rows per chunk (only the reduced phase is kept of each)."""
    pair = groups[0].pair
    block = max(int(run.chunk_rows), 1)
    meta = {c: [] for c in ("TIME", "ANTENNA1", "ANTENNA2")}
    phases, oks = [], []
    with open_set_rows(run.ref_ms, reference_sources(run)) as set_rows:
        for start in range(0, ref_rows.size, block):
            read = set_rows.reader(ref_rows[start:start + block])
            for c in meta:
                meta[c].append(read(c))
            phase, ok = _reduced_phase(run, groups, read)
            phases.append(phase)
            oks.append(ok)
    if not phases:
        n_corr = len(pair.ref.corr)
        return ({"TIME": np.zeros(0), "ANTENNA1": np.zeros(0, np.int64),
                 "ANTENNA2": np.zeros(0, np.int64)}, np.zeros((0, n_corr)),
                np.zeros((0, n_corr), bool))
    return {c: np.concatenate(v) for c, v in meta.items()}, np.concatenate(phases), \
        np.concatenate(oks)


def _reduced_phase(run, groups, read) -> Tuple[np.ndarray, np.ndarray]:
    """One block's (n_row, n_corr) reference phase and validity."""
    pair = groups[0].pair
    data = read(run.columns.ref_data)
    good = ~read("FLAG")
    if run.columns.ref_model:
        model = read(run.columns.ref_model)
        data = data * np.conj(model) / np.where(np.abs(model) > 0, np.abs(model), 1.0)
    if data.shape[1] == 1:
        phasor, ok = data[:, 0, :], good[:, 0, :]
    else:
        at = groups[0].channels.ref_freq if groups[0].channels is not None else pair.ref.freq
        phasor, ok = reduce_rows(data, good, np.asarray(pair.ref.chan_freq), at)
    ok = ok & (np.abs(phasor) > 0) & np.isfinite(phasor)
    return np.angle(phasor), ok


def _side_rate(time: np.ndarray, phase: np.ndarray) -> float:
    """Least-squares rate (rad/s) of a short run of samples, unwrapped step by step."""
    if time.size < 2:
        return 0.0
    y = np.unwrap(phase)
    x = time - time.mean()
    return float(np.dot(x, y - y.mean()) / np.dot(x, x))


def _continued_count(time: np.ndarray, phase: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Wrap count n_c (from 0) that makes phase + 2 pi n_c continuous, and each step's
    residual (rad, in [-pi, pi]: what the count had to decide on).

    Between consecutive samples a step > pi is a wrap.  Across a gap (a slew: more
    than 1.5 regular steps) the phase is carried by its rates instead: each side's
    rate over its last / first RATE_SAMPLES samples predicts the phase at the gap's
    middle, and the wrap count is what makes the two predictions meet; the
    troposphere's motion during the slew, beyond its linear part, is what is left to
    the Itoh condition.
    """
    dphase = np.diff(phase)
    if time.size > 2:
        dt = np.diff(time)
        regular = float(np.median(dt))
        for g in np.flatnonzero(dt > 1.5 * regular):
            left = slice(max(0, g + 1 - RATE_SAMPLES), g + 1)
            right = slice(g + 1, min(time.size, g + 1 + RATE_SAMPLES))
            half = 0.5 * dt[g]
            dphase[g] -= half * (_side_rate(time[left], phase[left])
                                 + _side_rate(time[right], phase[right]))
    steps = np.round(dphase / (2.0 * np.pi)).astype(np.int64)
    return np.concatenate([[0], -np.cumsum(steps)]), dphase - 2.0 * np.pi * steps


def switch_counts(run, groups: List, tgt_meta: Dict[str, np.ndarray],
                  tgt_rows: np.ndarray) -> SwitchCounts:
    """N per target row (``tgt_rows``: ascending rows of one target window, every field
    of ``groups``) and correlation, from the reference set's rows of the same fields."""
    pair = groups[0].pair
    ref_fields = [g.pair.ref.key[0] for g in groups]
    ref_rows = _window_rows(run, pair.ref.key[1], ref_fields)
    meta, phase, ok = _reference_series(run, groups, ref_rows)
    ref_codes = stations_of(run.ref_ms, run.ref_meta.antennas).codes
    tgt_codes = stations_of(run.target_ms, run.tgt_meta.antennas).codes
    rename = parse_antenna_map(run.opts.input.antenna_map)
    to_tgt = np.array([tgt_codes.index(rename.get(c, c)) if rename.get(c, c) in tgt_codes
                       else -1 for c in ref_codes])
    corr_map = correlation_map(pair.ref.corr, pair.tgt.corr)
    t_a1, t_a2 = tgt_meta["ANTENNA1"][tgt_rows], tgt_meta["ANTENNA2"][tgt_rows]
    t_time = tgt_meta["TIME"][tgt_rows]
    t_scan = tracking_scans(groups, t_time, tgt_meta["FIELD_ID"][tgt_rows])
    r_a1, r_a2 = to_tgt[meta["ANTENNA1"]], to_tgt[meta["ANTENNA2"]]
    counts = np.zeros((tgt_rows.size, len(pair.tgt.corr)), np.int64)
    steps: List[float] = []
    for p, q in sorted(set(zip(t_a1.tolist(), t_a2.tolist()))):
        mine = np.flatnonzero((t_a1 == p) & (t_a2 == q))
        for swapped, (a, b) in enumerate(((p, q), (q, p))):
            pick = np.flatnonzero((r_a1 == a) & (r_a2 == b))
            if not pick.size:
                continue
            for c, ref_c in enumerate(corr_map[swapped]):
                if ref_c < 0:
                    continue
                keep = pick[ok[pick, ref_c]]
                keep = keep[np.argsort(meta["TIME"][keep], kind="stable")]
                series = phase[keep, ref_c] * (-1.0 if swapped else 1.0)
                if not keep.size:
                    continue
                n_c, residual = _continued_count(meta["TIME"][keep], series)
                _scan_starts(meta["TIME"][keep], residual, n_c, t_time[mine], t_scan[mine],
                             counts[:, c], mine, steps)
    steps_deg = np.degrees(np.abs(np.asarray(steps))) if steps else np.zeros(0)
    return SwitchCounts(counts, int(steps_deg.size),
                        float(steps_deg.max()) if steps_deg.size else 0.0,
                        int((steps_deg > RISKY_STEP_DEG).sum()))


def _window_rows(run, ddid: int, fields) -> np.ndarray:
    """The reference set's rows of window ``ddid`` and ``fields``, from its DATA_DESC_ID and
    FIELD_ID read chunk by chunk."""
    block = max(int(run.chunk_rows), 1)
    found = []
    with open_set_rows(run.ref_ms, reference_sources(run)) as set_rows:
        n_rows = set_rows.n_rows
        for start in range(0, n_rows, block):
            n = min(block, n_rows - start)
            index = set_rows.index(["DATA_DESC_ID", "FIELD_ID"], start, n)
            here = (index["DATA_DESC_ID"] == ddid) & np.isin(index["FIELD_ID"], fields)
            found.append(start + np.flatnonzero(here))
    return np.concatenate(found) if found else np.zeros(0, np.int64)


def tracking_scans(groups: List, time: np.ndarray, field: np.ndarray) -> np.ndarray:
    """The transfer's own tracking scan of each row (SCAN_NUMBER, split where calibrate
    split it at long gaps: each group's ``grid.scans.scan_of_time``), numbered apart per field."""
    out = np.zeros(time.size, np.int64)
    for g, group in enumerate(groups):
        rows = field == group.pair.tgt.key[0]
        axis = np.asarray(group.grid.times)
        pos = np.clip(np.searchsorted(axis, time[rows]), 1, max(axis.size - 1, 1))
        nearest = np.where(np.abs(axis[pos - 1] - time[rows]) <= np.abs(axis[pos] - time[rows]),
                           pos - 1, pos) if axis.size > 1 else np.zeros(rows.sum(), np.int64)
        out[rows] = g * (1 << 32) + np.asarray(group.grid.scans.scan_of_time)[nearest]
    return out


def _scan_starts(ref_time, residual, n_c, tgt_time, tgt_scan, out, mine, steps) -> None:
    """``out[mine]`` = the continued count at the first reference sample of each target
    scan (at or after the scan's first row); the step's residual there into ``steps``."""
    for scan in np.unique(tgt_scan):
        rows = tgt_scan == scan
        first = int(np.searchsorted(ref_time, tgt_time[rows].min() - 1e-3))
        if first >= ref_time.size:
            continue
        out[mine[rows]] = n_c[first]
        if first > 0:
            steps.append(float(residual[first - 1]))
