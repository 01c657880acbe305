"""How many rows calibrate holds at once, from a memory budget (``--memory-budget``).

The budget defaults to 1 GB or half the machine's available memory, whichever
is smaller; ``--chunk-rows`` overrides what follows from it.  The model of a
run's peak resident memory is fitted to peaks measured on this machine
(docs/performance.md, "Memory budget"):

* a fixed part: the interpreter with numba, dask, dask-ms and python-casacore
  loaded (about 160 MB; 300 MB with a margin);
* a part per row of both bands for the whole run: each row's antenna pair kept
  by the index pass (2 bytes; hitops/calibrate/band_index.py), the rows written
  (1 byte per target row; hitops/calibrate/output.py) and, for a set read through
  dask-ms, the row numbers it keeps and the TaQL selection behind them.  A run
  without a cluster reads one-group sets with python-casacore (hitops/io/read.py,
  ``open_for_reading``): :data:`LOCAL_ORDER_BYTES_PER_ROW`, with a margin for a
  shuffled table's row numbers (4 bytes per row, hitops/io/time_sorted.py).  Through
  dask-ms (a cluster, or sets of several fields or windows): 26 bytes per row for
  a table stored in time order (21 measured at 10^7 rows per band before the pair
  keys were kept) and 42 for one dask-ms must sort to cut it into chunks (37-38
  measured before; see :func:`hitops.io.read.open_groups` for why that sort does
  not use dask-ms's grouping query);
* a part per target row of a time chunk (both bands' visibilities, flags, the
  (baseline, time) grids, phasors and outputs): about 96 bytes per correlation
  plus 30 per correlation and method, and the per-channel columns again for
  every further channel; with several chunks also the next chunk's read
  (:func:`read_bytes_per_row`), and for outputs to a processing set, written on a
  thread of their own beside that read (hitops/calibrate/chunk_io.py), the chunk
  being written once more;
* the tracker's own (:func:`tracker_bytes`): the smooth and antenna trackers work on
  the reference gridded over the chunk and its context, and the antenna tracker keeps
  every station's phase and segment over the whole track (16 bytes per station,
  correlation and time step, in two trackers at once).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

from ..errors import InputError

#: the default budget's ceiling (bytes)
DEFAULT_CEILING = 1_000_000_000
#: resident memory before any row is read (imports, numba kernels, dask), with a margin
FIXED_BYTES = 300_000_000
#: bytes per row (both bands) that dask-ms keeps for the whole run: its row numbers and
#: the TaQL selection behind them, for a table in time order and for one it sorts
ORDER_BYTES_PER_ROW = 26
UNSORTED_ORDER_BYTES_PER_ROW = 42
#: the same without dask-ms: 2 bytes of pair keys per row of both bands, 0.5 of rows written,
#: a shuffled table's row numbers (4 bytes per row, hitops/io/time_sorted.py), with a margin
LOCAL_ORDER_BYTES_PER_ROW = 8
#: the fewest target rows per chunk a run uses when the default budget cannot be kept (one
#: channel; a row of n_chan channels is n_chan times larger: see min_chunk_rows)
MIN_CHUNK_ROWS = 100_000
UNITS = {"": 1, "B": 1, "KB": 1e3, "MB": 1e6, "GB": 1e9, "TB": 1e12,
         "KIB": 2 ** 10, "MIB": 2 ** 20, "GIB": 2 ** 30}


def available_bytes() -> int:
    """MemAvailable of /proc/meminfo (Linux); the physical memory elsewhere."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def parse_budget(text) -> int:
    """Bytes from ``auto`` or a size such as ``800MB``, ``2GB``, ``1.5GiB`` or a number."""
    value = str(text if text is not None else "auto").strip()
    if value.lower() == "auto":
        return int(min(DEFAULT_CEILING, 0.5 * available_bytes()))
    match = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][0-9]+)?)\s*([A-Za-z]*)", value)
    unit = match.group(2).upper() if match else None
    if match is None or unit not in UNITS:
        raise InputError(f"--memory-budget {text}: give a size such as 800MB, 2GB or 1.5GiB "
                         "(or auto: 1 GB or half the available memory, whichever is smaller)")
    budget = int(float(match.group(1)) * UNITS[unit])
    if budget <= FIXED_BYTES:
        raise InputError(f"--memory-budget {text}: a run needs about {FIXED_BYTES / 1e6:.0f} MB "
                         "before it reads a row; give more (e.g. 1GB)")
    return budget


def bytes_per_row(n_corr: int, n_chan: int, n_methods: int) -> int:
    """Peak bytes per target row of a time chunk (both bands together)."""
    # DATA + FLAG of both bands, new FLAG, outputs; + 2: the usable-channel masks of a
    # per-channel transfer's reductions (both bands; 1.05 GB measured against 1.0 without)
    per_chan = 18 + 9 + 2 + 8 * n_methods
    return n_corr * (96 + 30 * n_methods + per_chan * max(n_chan - 1, 0))


#: bytes per target row and correlation that the smooth and antenna trackers add to a
#: chunk (the reference gridded over the chunk and its context, the segment and antenna
#: solves), with the rest of the model fitted to peaks measured on 2026-11-29
#: (docs/calibrate.md, "Memory budget"): the paper-size pair (1.2 M rows per band,
#: whose one-chunk runs peak at 0.84 and 0.93 GB) stays in one chunk, and 10^7-row runs
#: peak at 0.91-0.94 GB (1.007 GB: the smooth tracker on a Measurement Set v2).  Alone
#: the trackers measured 200-225 bytes more per row and correlation than the count
#: tracker; the count model's own margin holds the rest.
TRACKER_BYTES_PER_CORR = {"count": 0, "smooth": 80, "antenna": 80}


@dataclass(frozen=True)
class TrackerMemory:
    """What the run's tracker holds beside the chunk (:func:`tracker_bytes`)."""

    per_row: int        # bytes per target row of a chunk
    per_run: int        # bytes for the whole run


def tracker_bytes(tracker: str, n_corr: int, n_rows_target: int, n_ant: int) -> TrackerMemory:
    """The tracker's share of a run: per target row of a chunk, and the antenna tracker's
    whole-track records (every station's phase and segment, 16 bytes per station,
    correlation and time step, in two trackers at once: the writing pass's and the first
    pass's, which is also the one that plans the reads).  Its time steps are taken as the
    target's rows over its baselines, every baseline at every step; a set with fewer
    baselines per step has more steps than that."""
    per_row = n_corr * TRACKER_BYTES_PER_CORR.get(tracker, 0)
    if tracker != "antenna" or n_ant < 2:
        return TrackerMemory(per_row, 0)
    n_time = n_rows_target / (n_ant * (n_ant - 1) / 2)
    return TrackerMemory(per_row, int(2 * 16 * n_ant * n_corr * n_time))


def read_bytes_per_row(n_corr: int, n_chan: int) -> int:
    """Bytes per target row of one chunk as read (both bands' data and flags, the row
    grids and the tracker's gridded reference): what reading the next chunk while this
    one is worked on adds (hitops/calibrate/pipeline.py)."""
    return n_corr * (18 * n_chan + 60) + 64


def min_chunk_rows(n_chan: int) -> int:
    """The fewest rows a default-budget chunk has: MIN_CHUNK_ROWS visibilities per correlation
    (what keeps the per-chunk overheads small), at least 1000 rows.  In rows, not bytes, a
    64-channel chunk of 100 000 rows took 1.67 GB against the 1-GB default (bench_wideband)."""
    return max(1000, MIN_CHUNK_ROWS // max(n_chan, 1))


def rows_for_budget(budget: int, n_rows_both_bands: int, n_corr: int, n_chan: int,
                    n_methods: int, time_ordered: bool = True, strict: bool = True,
                    local: bool = False, writes_apart: bool = False,
                    tracker: TrackerMemory = TrackerMemory(0, 0)) -> int:
    """Target rows per time chunk that keep the run's peak within ``budget`` bytes.

    A run that fits in one chunk holds one; a run of several chunks also holds the
    next chunk's read while it works on one, and its chunks are smaller by that.
    ``strict``: a budget too small for a chunk of 1000 rows is an error (a budget
    the user gave); otherwise (the default budget) chunks have at least
    :func:`min_chunk_rows` rows, even where that exceeds the budget.  ``local``: the
    sets are read without dask-ms (no cluster, one group each), in either order.
    ``writes_apart``: the outputs go to a processing set, written beside the next read,
    so a run of several chunks may hold a third one (counted whole: an upper bound).
    ``tracker``: what the run's tracker adds (:func:`tracker_bytes`).
    """
    per_row = bytes_per_row(n_corr, n_chan, n_methods) + tracker.per_row
    # a run in one chunk reads every set in storage order: no sort, whatever the layout
    order_bytes = LOCAL_ORDER_BYTES_PER_ROW if local else ORDER_BYTES_PER_ROW
    room = budget - FIXED_BYTES - order_bytes * n_rows_both_bands - tracker.per_run
    if 2 * (max(room, 0) // per_row) >= n_rows_both_bands:
        return int(room // per_row)
    if not (time_ordered or local):
        room = (budget - FIXED_BYTES - UNSORTED_ORDER_BYTES_PER_ROW * n_rows_both_bands
                - tracker.per_run)
    held = per_row * (2 if writes_apart else 1) + read_bytes_per_row(n_corr, n_chan)
    rows = int(max(room, 0) // held)
    if not strict:
        return max(rows, min_chunk_rows(n_chan))
    if rows < 1000:
        raise InputError(f"--memory-budget {budget / 1e6:.0f} MB: the sets' {n_rows_both_bands} "
                         "rows leave no room for a chunk of data; give a larger budget (or "
                         "--chunk-rows)")
    return rows
