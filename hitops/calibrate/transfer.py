"""One time chunk of frequency phase transfer, split over baseline batches.

The pipeline (:mod:`hitops.calibrate.pipeline`) reads a chunk of rows, calls
:func:`plan_groups` and runs :func:`transfer_batch` on each baseline batch as
one task (:class:`hitops.calibrate.batch_tasks.BatchTasks`: a thread of this
process, or a task on a dask cluster): a :class:`TransferInputs` in (the group's rows, the chunk's scans,
the tracker's share, the n0 shifts), a :class:`TransferResult` out (each
method's phasors, the calibrated mask, what the task carried, the sample
counts and the n0 step's sums).  The reference wraps come from the tracker's
share (:class:`hitops.tracking.base.BatchWraps`): counted here by the count
tracker (continuing across chunks through a :class:`hitops.tracking.count.Carry`,
so the result does not depend on the chunk size; it restarts at every new
scan), sliced from the chunk's counts by the smooth and antenna trackers.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..kernels import fpt, wideband
from ..kernels.segments import SegmentSums, segment_run_sums
from ..tracking.base import BatchWraps
from ..tracking.count import Carry, count_scans


@dataclass
class BatchRows:
    """The rows one baseline batch's task reads, and its row grids.

    tgt_rows, ref_rows (n_bl, n_time): index into the row arrays, or -1; tgt_vis,
    tgt_ok (n_tgt, n_corr) (tgt_vis None: a per-channel read that needed only the rows'
    validity, hitops/calibrate/chunk_read.py); ref_vis, ref_ok (n_ref, n_corr_ref); ref_swapped
    (n_ref,); off_vis, off_ok (n_tgt, n_corr): the n0 step's offset reference (or
    model) when the task sums the step, else None.
    """

    tgt_rows: np.ndarray
    ref_rows: np.ndarray
    tgt_vis: np.ndarray
    tgt_ok: np.ndarray
    ref_vis: np.ndarray
    ref_ok: np.ndarray
    ref_swapped: np.ndarray
    off_vis: Optional[np.ndarray]
    off_ok: Optional[np.ndarray]


@dataclass
class TransferInputs:
    """Everything one baseline batch's transfer task needs (all group-local).

    corr_map (2, n_corr): the reference correlation of each target one (unswapped,
    swapped rows); scan_of_time (n_time,) and n_scan: the chunk's tracking scans;
    methods: method codes (:data:`hitops.kernels.fpt.METHOD_CODES`); ratio = r + eps;
    reference: the tracker's share of the chunk; tgt_carry: CWU's own count of the
    target phase, carried across chunks; offsets (n_bl, n_corr, n_scan): the n0
    shifts per scan of a writing pass, or None; segment_keys (n_bl, n_corr, n_time):
    sum the n0 step per segment (robust trackers' first pass), or None; nu_ref: the
    reference frequency of a per-channel transfer (hitops/calibrate/channels.py), which
    then also returns each cell's delay; offset_k (n_bl, n_corr, n_scan) int64: the n0
    integers behind ``offsets`` (the delay needs the turns, not only their phase).
    """

    rows: BatchRows
    corr_map: np.ndarray
    scan_of_time: np.ndarray
    n_scan: int
    methods: List[int]
    ratio: float
    eps: float
    reference: BatchWraps
    tgt_carry: Carry
    offsets: Optional[np.ndarray] = None
    segment_keys: Optional[np.ndarray] = None
    nu_ref: Optional[float] = None
    offset_k: Optional[np.ndarray] = None


@dataclass
class SampleCounts:
    """Target samples (row x correlation) and why some are not calibrated: disjoint causes,
    in this order, that add up to the samples left uncalibrated."""

    n_samples: int = 0
    target_invalid: int = 0
    no_reference_row: int = 0
    reference_invalid: int = 0
    other_uncalibrated: int = 0

    def add(self, other: "SampleCounts") -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    @property
    def flagged(self) -> int:
        return (self.target_invalid + self.no_reference_row + self.reference_invalid
                + self.other_uncalibrated)


@dataclass
class TransferResult:
    """One baseline batch's output.

    phasors: method code -> (n_bl, n_time, n_corr) complex64 factor per cell;
    calibrated (n_bl, n_time, n_corr) bool; ref_carry: what the tracker's share
    carried out (``ResolvedWraps.carry``); tgt_carry: CWU's target count after the
    chunk; wrap_events (n_bl, n_corr) int64 counted here; samples: the causes;
    scan_sums / scan_counts (n_bl, n_corr, n_scan): the n0 step's sums per scan, and
    segment_sums per segment (group-local baselines), when the task sums the step;
    delays: method code -> (n_bl, n_time, n_corr) float64 seconds across the target
    window (per-channel transfers only).
    """

    phasors: Dict[int, np.ndarray]
    calibrated: np.ndarray
    ref_carry: Optional[Carry]
    tgt_carry: Carry
    wrap_events: np.ndarray
    samples: SampleCounts
    scan_sums: Optional[np.ndarray] = None
    scan_counts: Optional[np.ndarray] = None
    segment_sums: Optional[SegmentSums] = None
    delays: Optional[Dict[int, np.ndarray]] = None


def transfer_batch(inputs: TransferInputs) -> TransferResult:
    """FPT of one baseline batch of one chunk (one task; inputs are group-local)."""
    rows = inputs.rows
    tgt_rows, ref_rows = rows.tgt_rows, rows.ref_rows
    n_bl, n_time = tgt_rows.shape
    n_corr = inputs.corr_map.shape[1]
    methods, scan_of_time = inputs.methods, inputs.scan_of_time
    identity = np.vstack([np.arange(n_corr), np.arange(n_corr)]).astype(np.int64)
    ref_phase, ref_valid = fpt.gather_phase(ref_rows, rows.ref_vis, rows.ref_ok,
                                            rows.ref_swapped, inputs.corr_map)
    if fpt.CWU in methods or rows.off_vis is not None:
        tgt_phase, tgt_valid = fpt.gather_phase(tgt_rows, rows.tgt_vis, rows.tgt_ok,
                                                np.zeros(rows.tgt_vis.shape[0], bool), identity)
    else:  # PWC and CFPT do not need the target phase itself
        tgt_valid = (wideband.gather_ok(tgt_rows, rows.tgt_ok) if rows.tgt_vis is None
                     else fpt.gather_valid(tgt_rows, rows.tgt_vis, rows.tgt_ok))
        tgt_phase = np.zeros((1, 1, 1))
    reference = inputs.reference.resolve(ref_phase, ref_valid, scan_of_time)
    tgt_wraps, tgt_carry = np.zeros((1, 1, 1), np.int64), inputs.tgt_carry
    if fpt.CWU in methods:
        tgt_wraps, tgt_carry = count_scans(tgt_phase, tgt_valid, scan_of_time, inputs.tgt_carry)
    offsets = inputs.offsets
    if offsets is None:
        offsets = np.zeros((n_bl, n_corr, inputs.n_scan))
    phasors = {}
    calibrated = None
    for method in methods:
        phasors[method], calibrated = fpt.transfer_phasors(
            tgt_rows, tgt_phase, tgt_valid, reference.ref_phase, reference.ref_valid,
            reference.ref_wraps, tgt_wraps, inputs.ratio, inputs.eps, method, offsets,
            scan_of_time)
    out = TransferResult(phasors=phasors, calibrated=calibrated, ref_carry=reference.carry,
                         tgt_carry=tgt_carry, wrap_events=reference.wrap_events,
                         samples=sample_causes(tgt_rows, ref_rows, tgt_valid, reference.ref_valid,
                                               calibrated))
    if inputs.nu_ref is not None:
        out.delays = channel_delays(inputs, reference, calibrated)
    offset_method = fpt.PWC if fpt.PWC in phasors else (fpt.CWU if fpt.CWU in phasors else None)
    if rows.off_vis is not None and offset_method is not None:
        off_phase, off_valid = fpt.gather_phase(tgt_rows, rows.off_vis, rows.off_ok,
                                                np.zeros(rows.off_vis.shape[0], bool), identity)
        out.scan_sums, out.scan_counts = fpt.offset_sums(
            tgt_phase, phasors[offset_method], calibrated, off_phase, off_valid, scan_of_time,
            inputs.n_scan)
        if inputs.segment_keys is not None:
            # robust trackers: the n0 step per segment (segments after long gaps and jumps)
            out.segment_sums = segment_run_sums(inputs.segment_keys, tgt_phase,
                                                phasors[offset_method], calibrated,
                                                off_phase, off_valid)
    return out


def channel_delays(inputs: TransferInputs, reference, calibrated) -> Dict[int, np.ndarray]:
    """Each method's delay per cell: PWC and CWU from the unwrapped reference phase (the
    two agree, GUIDE.md section 1), CFPT from the wrapped one."""
    n_bl, _, n_corr = calibrated.shape
    offset_k = inputs.offset_k
    if offset_k is None:
        offset_k = np.zeros((n_bl, n_corr, inputs.n_scan), np.int64)
    delays: Dict[int, np.ndarray] = {}
    for unwrap in (True, False):
        codes = [m for m in inputs.methods if (m != fpt.CFPT) == unwrap]
        if codes:
            delay = wideband.cell_delays(calibrated, reference.ref_phase, reference.ref_wraps,
                                         offset_k, inputs.scan_of_time, inputs.nu_ref, unwrap)
            delays.update({m: delay for m in codes})
    return delays


def sample_causes(tgt_rows, ref_rows, tgt_valid, ref_valid, calibrated) -> SampleCounts:
    """Why target samples are not calibrated: disjoint causes, in this order, that add up
    to the samples left uncalibrated (a sample flagged in the target and without a
    reference row counts once, as target-flagged; :func:`hitops.kernels.fpt.sample_cause_counts`
    in one pass over the cells)."""
    counts = fpt.sample_cause_counts(tgt_rows, ref_rows, tgt_valid, ref_valid, calibrated)
    return SampleCounts(*(int(n) for n in counts))


def plan_groups(n_bl: int, n_groups: int) -> List[np.ndarray]:
    """Baseline indices of each group (contiguous, nearly equal sizes)."""
    n_groups = max(1, min(n_groups, n_bl))
    return [g for g in np.array_split(np.arange(n_bl), n_groups) if g.size]


def batch_rows(bls: np.ndarray, tgt_grid: np.ndarray, ref_grid: np.ndarray,
               tgt_vis, tgt_ok, ref_vis, ref_ok, ref_swapped,
               off_vis: Optional[np.ndarray], off_ok: Optional[np.ndarray],
               local: bool = True) -> Tuple[BatchRows, Optional[np.ndarray]]:
    """The rows one baseline batch needs, its row grids, and the chunk rows it copied.

    ``local``: copy the group's rows into compact arrays (what a remote worker
    should receive; the second value says which chunk rows they are); otherwise
    share the chunk's arrays (threads) and index them through the chunk's row grids
    (the second value is None).
    """
    if not local:
        return BatchRows(tgt_grid[bls], ref_grid[bls], tgt_vis, tgt_ok, ref_vis, ref_ok,
                         ref_swapped, off_vis, off_ok), None

    def localise(grid, arrays):
        rows = grid[bls]
        used = rows >= 0
        picked = rows[used]
        local = np.full(rows.shape, -1, dtype=np.int64)
        local[used] = np.arange(picked.size)
        return local, picked, [None if a is None else a[picked] for a in arrays]

    tgt_local, tgt_picked, (tv, tok, ov, ook) = localise(tgt_grid, [tgt_vis, tgt_ok, off_vis, off_ok])
    ref_local, _, (rv, rok, rsw) = localise(ref_grid, [ref_vis, ref_ok, ref_swapped])
    return BatchRows(tgt_local, ref_local, tv, tok, rv, rok, rsw, ov, ook), tgt_picked
