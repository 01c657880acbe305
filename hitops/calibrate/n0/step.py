"""The n0 offset step: which 2 pi eps k each scan or segment of PWC/CWU carries.

Given the first pass's sums of the calibrated phase against the offset
reference (``--offset-reference-column``: a reference calibration;
``--offset-model``: ``point`` or a model column):

* count tracker (not ``segmented``): per baseline, correlation and scan, the lattice point nearest
  the circular mean (:func:`hitops.calibrate.n0.baseline.choose_offset`), applied
  as a phase offset by the writing pass;
* smooth tracker: the same per segment, added to the segment's wrap count;
* antenna tracker: integers per antenna and segment for the parallel hands,
  from one lattice solve over every baseline and both hands
  (:func:`hitops.calibrate.n0.antenna.antenna_offsets`), so closure phases are
  kept; the cross hands per baseline.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from ...kernels import fpt
from ...kernels.channel_offsets import channel_offset_sums
from ...kernels.segments import shifted_rows
from ...tracking.base import WrapTracker
from ...tracking.state import SEGMENT_KEY, apply_segment_offsets
from ..plan import GroupPlan, RunPlan
from .antenna import LatticeProblem, antenna_offsets
from .baseline import WindowRatios, choose_channel_offset, choose_offset
from .hands import HandPhases

log = logging.getLogger("hitops.calibrate")


@dataclass
class OffsetSolution:
    """The step's result (all empty when no step ran).

    ``offsets``: (n_bl, n_corr, n_scan) phase offsets of the count tracker (zeros
    for the robust trackers, whose integers are in ``segment_k``), None without a
    step; ``segment_k``: {(baseline, correlation, segment key): k}; ``antennas``
    and ``solves``: the antenna lattice's per-antenna entries and per-solve
    summaries (None when no lattice solve ran); ``series``: the report's entries;
    ``offset_k``: the count tracker's integers behind ``offsets`` (a per-channel
    transfer's delay needs the turns themselves).
    """

    offsets: Optional[np.ndarray] = None
    offset_k: Optional[np.ndarray] = None
    segment_k: Optional[Dict[tuple, int]] = None
    antennas: List[dict] = field(default_factory=list)
    solves: Optional[List[dict]] = None
    series: List[dict] = field(default_factory=list)

    @property
    def ran(self) -> bool:
        return self.offsets is not None


@dataclass
class OffsetSums:
    """What the first pass sums for the step: exp(i (Phi_ref - Phi_out)) over calibrated
    samples per (baseline, correlation, scan), ``scan_sums`` (complex128) and
    ``scan_counts`` (int64) (n_bl, n_corr, n_scan), and per segment,
    ``segment_sums`` {(baseline, correlation, segment key): [z, n]} (segmented trackers).

    ``window``: the step runs across a target window's channels; every z is then an
    (n_chan,) array, one sum per channel (``scan_sums`` (n_bl, n_corr, n_scan, n_chan)),
    and n counts the samples of all channels."""

    scan_sums: np.ndarray
    scan_counts: np.ndarray
    segment_sums: Dict[tuple, list] = field(default_factory=dict)
    window: Optional[WindowRatios] = None

    @classmethod
    def for_batch(cls, group: GroupPlan) -> "OffsetSums":
        """Empty sums for ``group``: across its target window's channels when it has several."""
        channels = group.channels
        return cls.empty(group.match.n_bl, group.n_corr, group.grid.scans.n_scan,
                         None if channels is None else channels.offset_window(group.eps))

    @classmethod
    def empty(cls, n_bl: int, n_corr: int, n_scan: int,
              window: Optional[WindowRatios] = None) -> "OffsetSums":
        chan = () if window is None else (window.ratios.size,)
        return cls(np.zeros((n_bl, n_corr, n_scan) + chan, dtype=np.complex128),
                   np.zeros((n_bl, n_corr, n_scan), dtype=np.int64), window=window)

    def add_channel_sums(self, index, sums, counts, segmented: bool) -> None:
        """Add :func:`hitops.kernels.channel_offsets.channel_offset_sums`' result: keyed by
        tracking segment (``segmented``) or by scan index."""
        for (b, c, key), z, n in zip(index.tolist(), sums, counts.sum(axis=1).tolist()):
            if segmented:
                entry = self.segment_sums.setdefault((b, c, key), [0j, 0])
                entry[0] = entry[0] + z
                entry[1] += n
            else:
                self.scan_sums[b, c, key] += z
                self.scan_counts[b, c, key] += n


def offset_step_needed(group: GroupPlan) -> bool:
    """False when PWC carries no n0 offset: an integer R on one target channel.  Across a
    window R_j = R_0 + (nu_j - nu_0)/nu_ref is not an integer off the centre, so a wrong
    count leaves a phase slope across the window, which the step can see."""
    if group.eps != 0.0:
        return True
    window = OffsetSums.for_batch(group).window
    if window is None:
        log.info("integer R: PWC has no n0 offset; the offset step is skipped")
        return False
    log.info("integer R at the target window's centre: the n0 step runs across the window's "
             "channels (R_j %.8g .. %.8g)", window.ratios.min(), window.ratios.max())
    return True


def channel_sums(sums: OffsetSums, group: GroupPlan, chunk, segment_keys, out) -> None:
    """Add one chunk's per-channel sums of the n0 step to ``sums`` (a first pass across a
    window's channels): per segment (``segment_keys`` (n_bl, n_corr, n_time), segmented
    trackers) or per scan.  ``chunk``: the :class:`hitops.calibrate.chunk_read.ChunkData`;
    ``out``: its transfer in row order (the pipeline's RowOutputs: PWC's, else CWU's,
    phasors and delays)."""
    method = fpt.PWC if fpt.PWC in out.phasor_rows else fpt.CWU
    keys = segment_keys
    if keys is None:
        scan = group.grid.scans.scan_of_time[chunk.t0:chunk.t1]
        keys = np.broadcast_to(scan[None, None, :], (group.match.n_bl, group.n_corr, scan.size))
    sums.add_channel_sums(*channel_offset_sums(
        chunk.tgt_grid, keys, chunk.tgt_data, chunk.tgt_flag, chunk.tgt_flag_row,
        out.phasor_rows[method], out.delay_rows[method], group.channels.chan_offset,
        chunk.off_data), segmented=segment_keys is not None)


def solve_offsets(run: RunPlan, group: GroupPlan, tracker: WrapTracker,
                  sums: OffsetSums) -> OffsetSolution:
    """The integers from the first pass's ``sums`` and its ``tracker``."""
    stage = time.perf_counter()
    match = group.match
    max_k, ambiguity = int(run.opts.n0.max_offset_wraps), float(run.opts.n0.offset_ambiguity_deg)
    shape = (match.n_bl, group.n_corr, group.grid.scans.n_scan)
    solution = OffsetSolution(offsets=np.zeros(shape), offset_k=np.zeros(shape, np.int64))
    if not tracker.segmented:
        _per_scan(solution, group, sums, max_k, ambiguity)
    else:
        # segmented trackers: the n0 step per segment (every scan starts one; long gaps and
        # jumps start more); k is added to the segment's wrap count
        segment_sums = sums.segment_sums
        solution.segment_k = {}
        if tracker.name == "antenna":
            segment_sums = _antenna_lattice(solution, group, segment_sums, tracker, max_k,
                                            ambiguity, sums.window)
        _per_segment(solution, group, segment_sums, max_k, ambiguity, sums.window)
    chosen = [e for e in solution.series if e.get("samples") and e.get("solve") != "antenna"]
    if chosen or solution.solves is None:
        log.info("offset step: n0 chosen per baseline for %d series (|k| <= %d); %d "
                 "ambiguous; k values: %s", len(chosen), max_k,
                 sum(bool(e.get("ambiguous")) for e in chosen),
                 ", ".join(f"{e['baseline']} {e['correlation']} s{e['scan']}"
                           + (f"/{e['segment']}" if "segment" in e else "")
                           + f": {e['k']}" for e in chosen[:12])
                 + (" ..." if len(chosen) > 12 else ""))
    run.timings["offset_solve"] = time.perf_counter() - stage
    return solution


def _antenna_lattice(solution: OffsetSolution, group: GroupPlan, sums, tracker: WrapTracker,
                     max_k: int, ambiguity: float, window: Optional[WindowRatios]):
    """Integers per antenna and segment for the parallel hands; returns the other sums."""
    match, scans = group.match, group.grid.scans
    antenna_corrs = {c for c, name in enumerate(match.corr_names)
                     if len(name) == 2 and name[0] == name[1]}
    # the first pass's antenna phases tie the two hands
    hands = None if tracker.antenna_phase is None else HandPhases(
        tracker.antenna_phase, tracker.antenna_segment, scans.scan_of_time)
    problem = LatticeProblem(
        ant1=match.ant1, ant2=match.ant2, antenna_names=list(group.antenna_names),
        baseline_names=match.baseline_names, corr_names=match.corr_names,
        scans=scans.scan_numbers, eps=group.eps, max_k=max_k, ambiguity_deg=ambiguity,
        refants=tuple(group.tracking.refants), segment_key=int(SEGMENT_KEY), window=window)
    found = antenna_offsets(sums, antenna_corrs, problem, hands=hands)
    solution.segment_k.update(found.segment_k)
    solution.series.extend(found.series)
    solution.antennas, solution.solves = found.antennas, found.solves
    _log_antenna_offsets(found.antennas, found.solves)
    return {key: v for key, v in sums.items() if key[1] not in antenna_corrs}


def _entry(choice, base: dict, segment: bool) -> dict:
    entry = dict(base)
    if choice is None:
        entry.update(k=0, samples=0, note="no sample to compare; offset 0")
        return entry
    entry.update(choice.as_dict())
    if choice.ambiguous:
        where = f"scan {entry['scan']}" + (f" segment {entry['segment']}" if segment else "")
        log.warning("offset step %s %s %s ambiguous: k = %d (residual %.2f deg) vs k = %d "
                    "(%.2f deg)%s", entry["baseline"], entry["correlation"], where, choice.k,
                    choice.residual_deg, choice.runner_up_k, choice.runner_up_residual_deg,
                    "" if segment else "; bound --max-offset-wraps or use a better offset "
                    "reference")
    return entry


def _choose(z, n, eps: float, max_k: int, ambiguity: float, window: Optional[WindowRatios]):
    """One series' k: on the window centre's lattice, or across the window's channels."""
    if window is None:
        return choose_offset(complex(z), int(n), eps, max_k, ambiguity)
    return choose_channel_offset(z, int(n), window, max_k, ambiguity)


def _per_segment(solution: OffsetSolution, group: GroupPlan, sums, max_k: int,
                 ambiguity: float, window: Optional[WindowRatios]) -> None:
    match, scan_numbers = group.match, group.grid.scans.scan_numbers
    for (b, c, key), (z, n) in sorted(sums.items()):
        choice = _choose(z, n, group.eps, max_k, ambiguity, window)
        base = {"baseline": match.baseline_names[b], "correlation": match.corr_names[c],
                "scan": int(scan_numbers[key // SEGMENT_KEY]), "segment": int(key % SEGMENT_KEY)}
        if choice is not None:
            solution.segment_k[(b, c, key)] = choice.k
        solution.series.append(_entry(choice, base, segment=True))


def _per_scan(solution: OffsetSolution, group: GroupPlan, sums: OffsetSums, max_k: int,
              ambiguity: float) -> None:
    match, scans = group.match, group.grid.scans
    for b in range(match.n_bl):
        for c in range(group.n_corr):
            for s in range(scans.n_scan):
                choice = _choose(sums.scan_sums[b, c, s], sums.scan_counts[b, c, s], group.eps,
                                 max_k, ambiguity, sums.window)
                base = {"baseline": match.baseline_names[b], "correlation": match.corr_names[c],
                        "scan": int(scans.scan_numbers[s])}
                if choice is not None:
                    solution.offsets[b, c, s] = 2 * math.pi * group.eps * choice.k
                    solution.offset_k[b, c, s] = choice.k
                solution.series.append(_entry(choice, base, segment=False))


def _log_antenna_offsets(antennas, solves) -> None:
    """One line per lattice solve (correlation, scan), warnings for ambiguous antennas."""
    for sv in solves:
        members = [e for e in antennas if e["correlation"] == sv["correlation"]
                   and e["scan"] == sv["scan"]]
        log.info("offset step %s scan %d (antenna lattice, %s, reference %s): %s; coherence "
                 "%.4f, baseline mismatch rms %.2f deg, worst %s %.2f deg",
                 sv["correlation"], sv["scan"], sv["method"], sv["reference"],
                 ", ".join(f"{e['antenna']}/{e['segment']} k={e['k']}"
                           + (f" (margin {e['margin_deg']:.1f} deg)"
                              if e.get("margin_deg") is not None else "") for e in members[:16])
                 + (" ..." if len(members) > 16 else ""),
                 sv["coherence"], sv["residual_rms_deg"] or 0.0, sv["worst_baseline"],
                 sv["worst_residual_deg"] or 0.0)
    for e in antennas:
        if e.get("ambiguous"):
            log.warning("offset step %s %s scan %d segment %d ambiguous: k = %d (residual "
                        "%.2f deg) vs k = %d (%.2f deg); margin %.2f deg < "
                        "--offset-ambiguity-deg", e["antenna"], e["correlation"], e["scan"],
                        e["segment"], e["k"], e["residual_deg"], e["runner_up_k"],
                        e["runner_up_residual_deg"], e["margin_deg"])
    log.info("offset step: %d antenna segments solved on the 2 pi eps k lattice in %d solves; "
             "%d ambiguous", len(antennas), len(solves),
             sum(bool(e.get("ambiguous")) for e in antennas))


def offset_shifted_rows(tgt_grid, eps: float, segment_k, seg_keys, phasors):
    """``phasors`` (PWC/CWU, (n_row, n_corr) each) multiplied by exp(i 2 pi eps k): new arrays.

    ``segment_k``: {(b, c, key): k} added to the wrap counts of a segment by the n0 step
    (robust trackers), which moves its PWC and CWU output by 2 pi eps k; ``seg_keys``
    (n_bl, n_corr, n_time) the chunk's segment keys; ``tgt_grid`` (n_bl, n_time) the
    chunk's target rows.  Used to shift the first pass's output instead of running the
    transfer again (one chunk); equal to the second pass to complex64 rounding.
    Returns the list of shifted phasors (the inputs themselves when nothing moves).
    """
    if seg_keys is None or not any(segment_k.values() if segment_k else ()):
        return list(phasors)
    k = apply_segment_offsets(np.zeros(seg_keys.shape, np.int64), seg_keys, segment_k)
    values = [v for v in segment_k.values()]
    k_min, k_max = min(values + [0]), max(values + [0])
    table = np.exp(1j * (2 * math.pi * eps) * np.arange(k_min, k_max + 1)).astype(np.complex64)
    grid = np.ascontiguousarray(tgt_grid)
    return [shifted_rows(grid, k, table, k_min, out) for out in phasors]

