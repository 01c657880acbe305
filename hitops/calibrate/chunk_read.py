"""Read one time chunk of both bands onto the (baseline, time) grid.

:func:`read_chunk` reads the chunk's target rows and its reference rows
(plus the tracker's context on either side), reduces channels to one visibility
per row (averaged, or with one ratio per channel referred by a delay fit to the
window's centre: hitops/calibrate/channels.py; a per-channel target whose phase no
method needs gives its rows' validity alone), and returns
a :class:`ChunkData`: per-row visibilities and validity, the row grids
``tgt_grid`` / ``ref_grid`` ((n_bl, n_time) row index or -1) and, for the
trackers that ask for it (smooth, antenna), the reference band gridded over the
extended time range (a :class:`hitops.tracking.base.ReferenceGrid`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from ..io import read as msio
from ..kernels import wideband
from ..kernels.fpt import row_grid
from ..tracking.base import ReferenceGrid
from ..tracking.grid import gather_grid
from .band_index import ROW_COLUMNS
from .channels import ChannelPlan, reduce_rows
from .chunks import ChunkRows
from .plan import GroupPlan, RunPlan


@dataclass
class ChunkData:
    """One chunk [t0, t1) of the union time axis, read."""

    t0: int
    t1: int
    tgt_rows: np.ndarray            # ROWID of the target rows, in grid order
    tgt_data: np.ndarray            # (n_row, n_chan, n_corr) the target column as stored
    tgt_flag: np.ndarray            # (n_row, n_chan, n_corr) the input flags
    tgt_flag_row: np.ndarray
    tgt_vis: np.ndarray             # (n_row, n_corr) channels reduced (see reduce)
    tgt_ok: np.ndarray
    ref_vis: np.ndarray             # (n_ref_row, n_corr_ref) reference, inside [t0, t1)
    ref_ok: np.ndarray
    ref_swapped: np.ndarray
    off_vis: Optional[np.ndarray]   # what the n0 step compares with (None without it, and
    off_ok: Optional[np.ndarray]    # when the step runs across the target's channels)
    tgt_grid: np.ndarray            # (n_bl, t1 - t0) index into the target rows, or -1
    ref_grid: np.ndarray
    reference: Optional[ReferenceGrid]   # the reference band over the tracker's extended
                                         # times, gridded (None: the tracker needs no grid)
    # the n0 step across the target's channels: the offset reference column as stored
    # (n_row, n_chan, n_corr); None for --offset-model point or without that step
    off_data: Optional[np.ndarray] = None


def average(data: np.ndarray, flag: np.ndarray, flag_row: np.ndarray):
    """(n_row, n_corr) visibility and validity from (n_row, n_chan, n_corr) data.

    One channel: the channel itself.  Several: the mean of unflagged finite
    channels.  Non-finite and zero values are rejected later by the kernels.
    """
    good = ~flag & ~flag_row[:, None, None]
    if data.shape[1] == 1:
        return data[:, 0, :], good[:, 0, :]
    good = good & np.isfinite(data)
    n_good = good.sum(axis=1)
    total = np.where(good, data, 0).sum(axis=1)
    vis = (total / np.maximum(n_good, 1)).astype(np.complex64)
    return vis, n_good > 0


def reduce(data: np.ndarray, flag: np.ndarray, flag_row: np.ndarray,
           channels: Optional[ChannelPlan], band: str):
    """One visibility per (row, correlation): :func:`average` on the single-ratio path;
    with a :class:`ChannelPlan`, the delay-fit reduction to the reference frequency
    (``band`` 'ref') or the target window's centre ('tgt')."""
    if channels is None:
        return average(data, flag, flag_row)
    good = ~flag & ~flag_row[:, None, None]
    if band == "ref":
        return reduce_rows(data, good, channels.ref_chan_freq, channels.ref_freq)
    return reduce_rows(data, good, channels.tgt_chan_freq, channels.tgt_centre)


def target_rows(data: np.ndarray, flag: np.ndarray, flag_row: np.ndarray,
                channels: Optional[ChannelPlan], phase_needed: bool):
    """The target's (n_row, n_corr) visibility and validity: :func:`reduce`, or with a
    per-channel transfer that needs no target phase (PWC, CFPT; the n0 step across the
    channels reads them itself) the validity alone and None: the delay fit's work and
    memory are saved, and the output does not change."""
    if channels is None or phase_needed:
        return reduce(data, flag, flag_row, channels, "tgt")
    return None, wideband.row_validity(data, flag, flag_row)


def _keep(rows: ChunkRows, keep: np.ndarray, flag_row: bool) -> ChunkRows:
    return ChunkRows(rows=rows.rows[keep], bl=rows.bl[keep], time=rows.time[keep],
                     swapped=rows.swapped[keep],
                     flag_row=rows.flag_row[keep] if flag_row else None, scan=None)


def _sigma(ref: dict, snr_source: str):
    if snr_source == "sigma":
        return np.asarray(ref["SIGMA"], dtype=np.float64)
    if snr_source == "weight":
        with np.errstate(divide="ignore"):
            return 1.0 / np.sqrt(np.asarray(ref["WEIGHT"], dtype=np.float64))
    return None


def _grid(n_bl: int, n_time: int, bl, time_index) -> np.ndarray:
    return row_grid(n_bl, n_time, np.asarray(bl), np.asarray(time_index))


def _meta_read(first, band) -> list:
    """The per-row metadata a chunk's read adds to the data columns: none when the checks
    kept the one chunk's rows or the band's metadata is held whole; TIME, ROWID and
    FLAG_ROW when the index pass kept the rows' pair keys; else every row column."""
    if first or band.whole:
        return []
    return (["TIME", "ROWID", "FLAG_ROW"] if band.pair_key is not None
            else ROW_COLUMNS + ["ROWID"])


def _chunk_rows(match, which: str, rows: slice, meta) -> ChunkRows:
    """A band's chunk rows on the grid, from the index pass where it kept them."""
    band = match.tgt if which == "tgt" else match.ref
    if band.whole:
        return match.index_rows(which, match.read_meta(which, rows, ROW_COLUMNS + ["ROWID"]))
    if band.pair_key is not None:
        return match.rows_from_index(which, rows, meta)
    return match.index_rows(which, meta)


def read_target(run: RunPlan, group: GroupPlan, k: int, scheduler) -> ChunkData:
    """Chunk ``k``'s target rows only: what writing a kept output needs."""
    columns, match = run.columns, group.match
    t0, t1 = group.bounds[k], group.bounds[k + 1]
    t_rows = match.row_numbers("tgt", t0, t1)
    read = list(dict.fromkeys([columns.target_data, columns.flag]
                              + _meta_read(None, match.tgt)))
    tgt, = msio.compute_columns([match.chunk_request("tgt", t_rows, read)], scheduler=scheduler)
    t_idx = _chunk_rows(match, "tgt", t_rows, tgt)
    flag = tgt[columns.flag]
    return ChunkData(t0=t0, t1=t1, tgt_rows=t_idx.rows, tgt_data=tgt[columns.target_data],
                     tgt_flag=flag, tgt_flag_row=t_idx.flag_row, tgt_vis=None, tgt_ok=None,
                     ref_vis=None, ref_ok=None, ref_swapped=None, off_vis=None, off_ok=None,
                     tgt_grid=_grid(match.n_bl, t1 - t0, t_idx.bl, t_idx.time - t0),
                     ref_grid=None, reference=None)


def read_chunk(run: RunPlan, group: GroupPlan, k: int, extent: Tuple[int, int],
               grid_reference: bool, scheduler) -> ChunkData:
    """Chunk ``k`` of ``group``.

    ``extent``: (t_lo, t_hi), the reference times the tracker needs (the chunk
    itself for count); ``grid_reference``: grid them for the tracker
    (``WrapTracker.grids_reference``); ``scheduler``: the dask scheduler of the reads.
    """
    columns, match = run.columns, group.match
    t0, t1 = group.bounds[k], group.bounds[k + 1]
    t_lo, t_hi = extent
    # the chunk's rows and their grid cells; the metadata is read with the data (or reused
    # from the checks when the whole track is one chunk)
    first = group.first_chunk if (group.n_chunks == 1 and (t_lo, t_hi) == (t0, t1)) else None
    t_rows = match.row_numbers("tgt", t0, t1)
    r_rows = match.row_numbers("ref", t_lo, t_hi)
    t_read = list(dict.fromkeys(columns.tgt + _meta_read(first, match.tgt)))
    r_read = list(dict.fromkeys(columns.ref + columns.snr + _meta_read(first, match.ref)))
    tgt, ref = msio.compute_columns([match.chunk_request("tgt", t_rows, t_read),
                                     match.chunk_request("ref", r_rows, r_read)],
                                    scheduler=scheduler)
    if first:
        t_idx, r_idx = first
    else:
        t_idx = _chunk_rows(match, "tgt", t_rows, tgt)
        r_idx = _chunk_rows(match, "ref", r_rows, ref)
    # reference rows whose station pair has no target baseline take no part
    keep = r_idx.bl >= 0
    if not keep.all():
        ref = {c: v[keep] for c, v in ref.items()}
        r_idx = _keep(r_idx, keep, flag_row=True)
    if columns.flag != "FLAG":   # --overwrite: the flags before hitops's first run
        tgt["FLAG"] = tgt.pop(columns.flag)
    channels = group.channels
    across = channels is not None and channels.across_channels
    # the target's phase at the window centre: CWU's own count, and an n0 step on one channel
    phase_needed = "cwu" in run.methods or (bool(columns.offset) and not across)
    tvis, tok = target_rows(tgt[columns.target_data], tgt["FLAG"], t_idx.flag_row, channels,
                            phase_needed)
    ref_data = ref[columns.ref_data]
    if columns.ref_model and channels is not None:
        # the model divides out channel by channel, before the channels are reduced
        ref_data = ref_data * np.conj(ref[columns.ref_model])
    rvis, rok = reduce(ref_data, ref["FLAG"], r_idx.flag_row, channels, "ref")
    if columns.ref_model and channels is None:
        mvis, _ = average(ref[columns.ref_model], np.zeros_like(ref["FLAG"]),
                          np.zeros_like(r_idx.flag_row))
        rvis = rvis * np.conj(mvis)
    reference = None
    if grid_reference:
        ext_grid = _grid(match.n_bl, t_hi - t_lo, r_idx.bl, r_idx.time - t_lo)
        reference = ReferenceGrid(t_lo, t_hi, *gather_grid(
            ext_grid, rvis, rok, r_idx.swapped, match.corr_map,
            _sigma(ref, group.tracking.snr_source)))
        del ext_grid
        inner = (r_idx.time >= t0) & (r_idx.time < t1)
        rvis, rok = rvis[inner], rok[inner]
        r_idx = _keep(r_idx, inner, flag_row=False)
    ovis = ook = off_data = None
    if columns.offset and across:
        # the n0 step across the channels compares channel by channel (a point model: none)
        if not (columns.offset_is_model and columns.model is None):
            off_data = tgt[columns.offset]
    elif columns.offset and columns.offset_is_model and columns.model is None:
        ovis = np.ones(tvis.shape, np.complex64)          # --offset-model point
        ook = np.ones(tvis.shape, bool)
    elif columns.offset:
        ovis, ook = reduce(tgt[columns.offset], tgt["FLAG"], t_idx.flag_row, channels, "tgt")
    n_t = t1 - t0
    return ChunkData(t0=t0, t1=t1, tgt_rows=t_idx.rows, tgt_data=tgt[columns.target_data],
                     tgt_flag=tgt["FLAG"], tgt_flag_row=t_idx.flag_row, tgt_vis=tvis, tgt_ok=tok,
                     ref_vis=rvis, ref_ok=rok, ref_swapped=r_idx.swapped, off_vis=ovis,
                     off_ok=ook, tgt_grid=_grid(match.n_bl, n_t, t_idx.bl, t_idx.time - t0),
                     ref_grid=_grid(match.n_bl, n_t, r_idx.bl, r_idx.time - t0),
                     reference=reference, off_data=off_data)
