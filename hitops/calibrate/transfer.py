"""One time chunk of frequency phase transfer, split over baseline groups.

The pipeline (:mod:`hitops.calibrate.pipeline`) reads a chunk of rows, calls
:func:`plan_groups` and runs :func:`transfer_group` on each baseline group
as a dask task.  Wrap counting continues across chunks through a
:class:`hitops.tracking.count.Carry` (the last valid reference sample of each series and its
count), so the result does not depend on the chunk size; it restarts at
every new scan.
"""

from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np

from ..kernels import fpt
from ..tracking.count import count_scans, wrap_events


def transfer_group(g: Dict) -> Dict:
    """FPT of one baseline group of one chunk (a dask task; inputs are group-local).

    Keys of ``g``: tgt_rows, ref_rows (n_bl, n_time) local row indices;
    tgt_vis, tgt_ok (n_tgt, n_corr); ref_vis, ref_ok (n_ref, n_corr_ref);
    ref_swapped (n_ref,); corr_map (2, n_corr); scan_of_time (n_time,);
    n_scan; methods (list of method codes); ratio; eps;
    ref_model (n_bl, n_corr, n_time) or None: antenna mode's unwrapped model phase of
    each baseline (NaN where not modelled); it replaces the baseline's own phase;
    ref_wraps, ref_exclude (n_bl, n_corr, n_time) or None: reference wrap counts
    and excluded reference samples from the tracker (:mod:`hitops.tracking`);
    ref_carry, tgt_carry (Carry); offsets (n_bl, n_corr, n_scan) or None;
    off_vis, off_ok (n_tgt, n_corr) or None.
    """
    tgt_rows, ref_rows = g["tgt_rows"], g["ref_rows"]
    n_bl, n_time = tgt_rows.shape
    n_corr = g["corr_map"].shape[1]
    identity = np.vstack([np.arange(n_corr), np.arange(n_corr)]).astype(np.int64)
    ref_phase, ref_valid = fpt.gather_phase(ref_rows, g["ref_vis"], g["ref_ok"],
                                            g["ref_swapped"], g["corr_map"])
    if fpt.CWU in g["methods"] or g.get("off_vis") is not None:
        tgt_phase, tgt_valid = fpt.gather_phase(tgt_rows, g["tgt_vis"], g["tgt_ok"],
                                                np.zeros(g["tgt_vis"].shape[0], bool), identity)
    else:  # PWC and CFPT do not need the target phase itself
        tgt_valid = fpt.gather_valid(tgt_rows, g["tgt_vis"], g["tgt_ok"])
        tgt_phase = np.zeros((1, 1, 1))
    scan_of_time = g["scan_of_time"]
    robust = g.get("ref_wraps") is not None
    if robust:
        # counts from the smooth/antenna tracker (whole array, with context across chunks)
        ref_wraps, ref_carry = g["ref_wraps"], g["ref_carry"]
        ref_phase, ref_valid = tracked_reference(ref_phase, ref_valid, g.get("ref_exclude"),
                                                 g.get("ref_model"))
    else:
        ref_wraps, ref_carry = count_scans(ref_phase, ref_valid, scan_of_time, g["ref_carry"])
    tgt_wraps, tgt_carry = np.zeros((1, 1, 1), np.int64), g["tgt_carry"]
    if fpt.CWU in g["methods"]:
        tgt_wraps, tgt_carry = count_scans(tgt_phase, tgt_valid, scan_of_time, g["tgt_carry"])
    offsets = g["offsets"]
    if offsets is None:
        offsets = np.zeros((n_bl, n_corr, g["n_scan"]))
    phasors = {}
    calibrated = None
    for method in g["methods"]:
        phasors[method], calibrated = fpt.transfer_phasors(
            tgt_rows, tgt_phase, tgt_valid, ref_phase, ref_valid, ref_wraps, tgt_wraps,
            g["ratio"], g["eps"], method, offsets, scan_of_time)
    out = {"phasors": phasors, "calibrated": calibrated, "ref_carry": ref_carry,
           "tgt_carry": tgt_carry}
    # wrap events per series (|steps| of n), for the log and report
    steps = wrap_events(np.ascontiguousarray(ref_wraps), scan_of_time)
    if robust:   # the robust tracker counts its own wrap events across chunks
        steps = np.zeros_like(steps)
    elif n_time and scan_of_time[0] == g["ref_carry"].last_scan and g["ref_carry"].has_last.any():
        # the first sample continues the previous chunk's scan: its step counts too
        first = ref_wraps[:, :, 0] - np.where(g["ref_carry"].has_last, g["ref_carry"].count, 0)
        steps = steps + np.abs(np.where(g["ref_carry"].has_last, first, 0))
    out["wrap_events"] = steps
    out.update(sample_causes(tgt_rows, ref_rows, tgt_valid, ref_valid, calibrated, n_corr))
    offset_method = fpt.PWC if fpt.PWC in phasors else (fpt.CWU if fpt.CWU in phasors else None)
    if g.get("off_vis") is not None and offset_method is not None:
        off_phase, off_valid = fpt.gather_phase(tgt_rows, g["off_vis"], g["off_ok"],
                                                np.zeros(g["off_vis"].shape[0], bool), identity)
        out["offset_sums"], out["offset_counts"] = fpt.offset_sums(
            tgt_phase, phasors[offset_method], calibrated, off_phase, off_valid, scan_of_time,
            g["n_scan"])
    if g.get("segment_keys") is not None and "offset_sums" in out:
        # robust trackers: the n0 step per segment (segments after long gaps and jumps)
        from ..kernels.segments import segment_run_sums
        out["segment_sums"] = segment_run_sums(g["segment_keys"], tgt_phase,
                                                  phasors[offset_method], calibrated,
                                                  off_phase, off_valid)
    return out



def tracked_reference(ref_phase, ref_valid, exclude, model):
    """The reference phase and validity a robust tracker's output leaves to transfer.

    ``exclude``: reference samples after a jump (--jump-action flag), or None;
    ``model``: antenna mode's unwrapped model phase (NaN where not modelled), or None.
    """
    if exclude is not None:
        ref_valid = ref_valid & ~exclude
    if model is not None and np.isfinite(model).any():
        # antenna mode: the baseline's reference phase is its antenna model (the counts
        # already belong to it), so the transferred phase closes on every triangle;
        # correlations without a model (cross-hands) keep their own phase
        modelled = np.isfinite(model)
        antenna_corr = modelled.any(axis=(0, 2))
        ref_phase = np.where(modelled, (model + np.pi) % (2 * np.pi) - np.pi, ref_phase)
        ref_valid = np.where(antenna_corr[None, :, None], ref_valid & modelled, ref_valid)
    return ref_phase, ref_valid


def sample_causes(tgt_rows, ref_rows, tgt_valid, ref_valid, calibrated, n_corr: int) -> Dict:
    """Why target samples are not calibrated: disjoint causes, in this order, that add up
    to the samples left uncalibrated (a sample flagged in the target and without a
    reference row counts once, as target-flagged)."""
    has_tgt = tgt_rows >= 0
    has_ref = ref_rows >= 0
    tgt_cell = has_tgt[:, None, :]
    tgt_bad = tgt_cell & ~tgt_valid
    no_ref = tgt_cell & tgt_valid & ~has_ref[:, None, :]
    ref_bad = tgt_cell & tgt_valid & has_ref[:, None, :] & ~ref_valid
    not_calibrated = ~np.swapaxes(calibrated, 1, 2)   # (n_bl, n_time, n_corr) -> (n_bl, n_corr, n_time)
    return {"n_samples": int(has_tgt.sum()) * n_corr, "target_invalid": int(tgt_bad.sum()),
            "no_reference_row": int(no_ref.sum()), "reference_invalid": int(ref_bad.sum()),
            "other_uncalibrated": int((tgt_cell & not_calibrated & ~tgt_bad & ~no_ref
                                       & ~ref_bad).sum())}

def plan_groups(n_bl: int, n_groups: int) -> List[np.ndarray]:
    """Baseline indices of each group (contiguous, nearly equal sizes)."""
    n_groups = max(1, min(n_groups, n_bl))
    return [g for g in np.array_split(np.arange(n_bl), n_groups) if g.size]


def group_inputs(bls: np.ndarray, tgt_grid: np.ndarray, ref_grid: np.ndarray,
                 tgt_vis, tgt_ok, ref_vis, ref_ok, ref_swapped,
                 off_vis: Optional[np.ndarray], off_ok: Optional[np.ndarray],
                 local: bool = True) -> Dict:
    """The rows one baseline group needs, and its row grids.

    ``local``: copy the group's rows into compact arrays (what a remote worker
    should receive); otherwise share the chunk's arrays (threads) and index
    them through the chunk's row grids.
    """
    if not local:
        rows = tgt_grid[bls]
        return {"tgt_rows": rows, "ref_rows": ref_grid[bls], "tgt_vis": tgt_vis,
                "tgt_ok": tgt_ok, "ref_vis": ref_vis, "ref_ok": ref_ok,
                "ref_swapped": ref_swapped, "off_vis": off_vis, "off_ok": off_ok,
                "tgt_picked": None}

    def localise(grid, arrays):
        rows = grid[bls]
        used = rows >= 0
        picked = rows[used]
        local = np.full(rows.shape, -1, dtype=np.int64)
        local[used] = np.arange(picked.size)
        return local, picked, [None if a is None else a[picked] for a in arrays]

    tgt_local, tgt_picked, (tv, tok, ov, ook) = localise(tgt_grid, [tgt_vis, tgt_ok, off_vis, off_ok])
    ref_local, _, (rv, rok, rsw) = localise(ref_grid, [ref_vis, ref_ok, ref_swapped])
    return {"tgt_rows": tgt_local, "ref_rows": ref_local, "tgt_vis": tv, "tgt_ok": tok,
            "ref_vis": rv, "ref_ok": rok, "ref_swapped": rsw, "off_vis": ov, "off_ok": ook,
            "tgt_picked": tgt_picked}
