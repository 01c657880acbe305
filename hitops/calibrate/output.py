"""Everything a calibrate run changes in the target set, in one transaction.

While the run goes on, every output column and the new flags are written under
``HITOPS_PARTIAL_*`` names; FLAG and the final column names are touched only by
:meth:`OutputTransaction.commit`, once every chunk is written.  A failure or an
interrupt before then (:meth:`OutputTransaction.rollback`) drops the staging
columns and leaves the set as it was; a killed run leaves only staging columns,
which no reader takes for a result and the next run removes
(:func:`drop_stale_columns`).
"""

from __future__ import annotations

import logging
import time
from typing import Dict, List, Optional

import numpy as np

from ..errors import RollbackError
from ..io import access
from ..io import read as msio
from ..kernels.wideband import rotate_channels
from ..io import tables

log = logging.getLogger("hitops.calibrate")

FLAG_BACKUP = "FLAG_HITOPS_BACKUP"
STAGING_PREFIX = "HITOPS_PARTIAL_"
STAGING_FLAG = STAGING_PREFIX + "FLAG"
VIS_DIMS = ("row", "chan", "corr")
#: bucket size of a StandardStMan output column (that of the simulator's and CASA's
#: small columns; casacore's default of 256 bytes makes millions of buckets)
SSM_BUCKET_BYTES = 1 << 18
#: rows per tile, and the tile cache's ceiling, of a tiled output written in scattered
#: rows (see OutputTransaction.create_columns)
SCATTERED_TILE_ROWS = 1024
SCATTERED_CACHE_BYTES = 16 << 20


def like_dminfo(dminfo: Dict, name: str, taken=(), scattered: bool = False,
                fixed_shape: bool = False) -> Dict:
    """A data manager of the same kind as ``dminfo`` (a column's) for new column ``name``.

    A tiled column gives a tiled one with its tile shape: a TiledColumnStMan when
    the column copied is one and its description fixes the cell shape
    (``fixed_shape``), otherwise a TiledShapeStMan.  Both store the same cells; the
    TiledColumnStMan is the cheaper one to add, since a TiledShapeStMan records a
    shape per row as the column is made (10^7 rows: 0.07 s against 0.3-0.5 s to add
    and close, measured).  ``scattered`` (rows written in many short runs all over
    the table): tiles of :data:`SCATTERED_TILE_ROWS` rows and a tile cache of at most
    :data:`SCATTERED_CACHE_BYTES`.  Anything else gives a StandardStMan.

    ``taken``: data manager names the table already uses.  A column keeps its data
    manager's name when it is renamed, so the column a run staged as
    HITOPS_PARTIAL_PWC_DATA and renamed to PWC_DATA still owns
    'HITOPS_PARTIAL_PWC_DATA_TSM' when the next run stages it again.
    """
    kind = dminfo.get("TYPE", "StandardStMan")
    spec = dminfo.get("SPEC", {})
    if kind.startswith("Tiled"):
        keep = {"DEFAULTTILESHAPE": spec["DEFAULTTILESHAPE"]} if "DEFAULTTILESHAPE" in spec else {}
        if scattered and "DEFAULTTILESHAPE" in keep:
            shape = np.array(keep["DEFAULTTILESHAPE"], dtype=np.int32)
            shape[-1] = min(int(shape[-1]), SCATTERED_TILE_ROWS)
            keep = {"DEFAULTTILESHAPE": shape, "MAXIMUMCACHESIZE": SCATTERED_CACHE_BYTES}
        if kind == "TiledColumnStMan" and fixed_shape and "DEFAULTTILESHAPE" in keep:
            kind, suffix, spec = "TiledColumnStMan", "TCM", keep
        else:
            kind, suffix, spec = "TiledShapeStMan", "TSM", keep
    else:
        kind, suffix, spec = "StandardStMan", "SSM", {"BUCKETSIZE": SSM_BUCKET_BYTES}
    taken, dm_name, n = set(taken), f"{name}_{suffix}", 1
    while dm_name in taken:
        n += 1
        dm_name = f"{name}_{suffix}{n}"
    return {"TYPE": kind, "NAME": dm_name, "SPEC": spec}


def fixed_cell_shape(desc: Dict) -> bool:
    """True when a column description (casacore's getcoldesc) fixes its cells' shape."""
    # casacore's ColumnDesc option FixedShape is bit 4 (tables/Tables/ColumnDesc.h)
    return bool(int(desc.get("option", 0)) & 4) and len(desc.get("shape", [])) > 0


def dm_names(table) -> set:
    """The data manager names an open casacore table uses."""
    return {dm.get("NAME") for dm in table.getdminfo().values()}


def drop_stale_columns(target_ms: str) -> None:
    """Remove staging columns left by a run that was killed (they never hold a result)."""
    with tables.main_table(target_ms) as t:
        stale = [c for c in t.colnames() if c.startswith(STAGING_PREFIX)]
    if stale:
        with tables.main_table(target_ms, writable=True) as t:
            t.removecols(stale)
        log.warning("removed %s from %s: unfinished columns of an earlier run that was "
                    "stopped", ", ".join(stale), target_ms)


class OutputTransaction:
    """This run's changes to the target set: staging columns, FLAG, commit and rollback.

    ``outputs``: method -> final column name; ``target_column``: the column whose
    description the outputs copy; ``chunk_rows``: rows per block when FLAG is
    copied at the commit (the run's memory bound).
    """

    #: the writes go to the table the run reads: on the reads' thread, after them
    #: (hitops/calibrate/chunk_io.py)
    writes_apart = False

    def __init__(self, target_ms: str, outputs: Dict[str, str], target_column: str,
                 n_rows: Optional[int], chunk_rows: int, direct_writes: bool = False):
        self.target_ms = target_ms
        self.outputs = dict(outputs)
        self.target_column = target_column
        self.chunk_rows = max(1, int(chunk_rows))
        # no dask-ms handle on the set (one chunk read by python-casacore): write with it too
        self.direct_writes = bool(direct_writes)
        self.staging = {m: STAGING_PREFIX + col for m, col in outputs.items()}
        self.created = list(self.staging.values()) + [STAGING_FLAG]
        if n_rows is None:   # every row of the table (a run may cover several groups)
            with tables.main_table(target_ms) as t:
                n_rows = t.nrows()
        self.rows_written = np.zeros(int(n_rows), dtype=bool)
        # rows whose new flags are staged: a chunk whose new flags equal FLAG stages none
        self.flags_staged = np.zeros(int(n_rows), dtype=bool)
        self.backup_written = False
        self.flag_written = False
        # the staged flags' column: made when a chunk first stages flags (direct writes) or
        # with the outputs; ``scattered`` as create_columns was told
        self.flag_column_made = False
        self.scattered = False

    def check_space(self) -> None:
        """Refuse before writing when the staging columns (and a backup) cannot fit."""
        with tables.main_table(self.target_ms) as t:
            n_row = t.nrows()
            cell = t.getcell(self.target_column, 0) if n_row else np.zeros((1, 1))
            backup_needed = FLAG_BACKUP not in t.colnames()
        n_cells = n_row * int(np.prod(cell.shape))
        # complex64 outputs, the staged flags, the backup (casacore stores Bool as bits in
        # tiled columns and bytes in others: count bytes)
        n_bytes = n_cells * (8 * len(self.staging) + 1 + (1 if backup_needed else 0))
        access.require_free_space(self.target_ms, n_bytes,
                                  f"{', '.join(self.outputs.values())} and FLAG")

    def create_columns(self, scattered: bool = False) -> List[str]:
        """Create the staging columns before anything is read or written.

        Each takes the description of the column it copies and a data manager of
        the same kind (:func:`like_dminfo`): a tiled DATA gives tiled outputs, which
        take a time-ordered table's chunks as sequential writes (10^7 rows: 0.46 s
        against 2.06 s for the StandardStMan column dask-ms would add).
        ``scattered``: the chunks' rows are spread over the whole table (a table
        not stored in time order, cut into several chunks); the tiles are then
        short and their cache bounded, since with the copied 32768-row tiles
        casacore kept every touched tile (1.6 GB peak at 10^7 rows against 1.29 GB;
        writing 0.87 s against 2.3 s for a StandardStMan, measured).
        Created here rather than by dask-ms's write: a dask.distributed scheduler
        and its workers that hold the table open keep the old column list, and
        casacore then refuses to open it again ("another process changed the
        number of columns").  With direct writes (no dask-ms handle on the set) the
        staged flags' column is made only when a chunk first stages flags
        (:meth:`_flag_column`): a run whose flags equal FLAG never makes it (0.25 s of
        a 10^7-row run, measured).
        """
        self.scattered = scattered
        new = [(c, self.target_column) for c in self.created if c != STAGING_FLAG]
        if not self.direct_writes:
            new.append((STAGING_FLAG, "FLAG"))
        self._add_columns(new)
        self.flag_column_made = not self.direct_writes
        return [n for n, _ in new]

    def _add_columns(self, new) -> None:
        """Add the columns (name, the column it copies) to the target set."""
        with tables.main_table(self.target_ms, writable=True) as t:
            t.lock(write=True)
            for name, like in new:
                desc = t.getcoldesc(like)
                desc["name"] = name
                t.addcols(tables.column_description(name, desc),
                          like_dminfo(t.getdminfo(like), name, dm_names(t), self.scattered,
                                      fixed_shape=fixed_cell_shape(desc)))

    def _flag_column(self) -> str:
        """The staged flags' column, made now if it is not there yet."""
        if not self.flag_column_made:
            self._add_columns([(STAGING_FLAG, "FLAG")])
            self.flag_column_made = True
        return STAGING_FLAG

    def write_chunk(self, rows: np.ndarray, data: np.ndarray, phasors: Dict[str, np.ndarray],
                    new_flag: np.ndarray, scheduler=None,
                    delays: Optional[Dict[str, np.ndarray]] = None,
                    chan_offset: Optional[np.ndarray] = None,
                    flag_read: Optional[np.ndarray] = None) -> None:
        """One chunk's outputs (data times each method's phasor) and new flags, staged.

        ``rows`` (n,) target rows; ``data`` (n, n_chan, n_corr); ``phasors``:
        method -> (n, n_corr); ``new_flag`` (n, n_chan, n_corr); ``delays``: method ->
        (n, n_corr) seconds across the window, channel k at ``chan_offset[k]`` Hz from the
        phasor's frequency (per-channel transfers: hitops/calibrate/channels.py);
        ``flag_read``: FLAG at ``rows`` as this run read it (n, n_chan, n_corr), or None (read
        again here when it is needed).
        """
        if delays is None:
            outputs = {m: (data * p[:, None, :]).astype(np.complex64, copy=False)
                       for m, p in phasors.items()}
        else:
            outputs = {m: rotate_channels(data, p, delays[m], chan_offset)
                       for m, p in phasors.items()}
        self.write_outputs(rows, outputs, new_flag, scheduler, flag_read)

    def write_outputs(self, rows: np.ndarray, outputs: Dict[str, np.ndarray],
                      new_flag: np.ndarray, scheduler=None,
                      flag_read: Optional[np.ndarray] = None) -> None:
        """One chunk's finished outputs (method -> (n, n_chan, n_corr), corrected already)
        and new flags, staged; ``flag_read`` as in :meth:`write_chunk`."""
        arrays = {self.staging[m]: np.asarray(out).astype(np.complex64, copy=False)
                  for m, out in outputs.items()}
        stage_flags = not self.direct_writes or self._flags_change(rows, new_flag, flag_read)
        if stage_flags:
            arrays[self._flag_column()] = new_flag
        msio.write_main_columns(self.target_ms, rows, arrays,
                                {name: VIS_DIMS for name in arrays}, scheduler=scheduler,
                                direct=self.direct_writes)
        self.rows_written[rows] = True
        if stage_flags:
            self.flags_staged[rows] = True

    def flags_now(self, set_rows, rows: np.ndarray) -> np.ndarray:
        """(n, n_chan, n_corr) the flags this run has given ascending ``rows`` so far, read
        through ``set_rows`` (hitops/calibrate/set_rows.py: the target's open main
        table): the staged ones where it staged them, FLAG elsewhere (a chunk whose new
        flags equalled FLAG staged none; a row not written keeps FLAG)."""
        rows = np.asarray(rows)
        flags = set_rows.reader(rows)("FLAG")
        staged = self.flags_staged[rows]
        if staged.any():
            flags[staged] = set_rows.reader(rows[staged])(STAGING_FLAG)
        return flags

    def restage(self, rows: np.ndarray, outputs: Dict[str, np.ndarray],
                new_flag: Optional[np.ndarray] = None) -> None:
        """Staged output columns (staging names) rewritten at ``rows`` by a later step of the
        same run (``--calibrator-field``), and their new flags when given: recorded as
        staged, so that the commit carries them into FLAG."""
        arrays = dict(outputs)
        if new_flag is not None:
            arrays[self._flag_column()] = new_flag
        msio.write_main_columns(self.target_ms, rows, arrays, {n: VIS_DIMS for n in arrays},
                                direct=self.direct_writes)
        if new_flag is not None:
            self.flags_staged[rows] = True

    def _flags_change(self, rows: np.ndarray, new_flag: np.ndarray,
                      flag_read: Optional[np.ndarray] = None) -> bool:
        """Whether ``new_flag`` differs from FLAG anywhere at ``rows``: ``flag_read`` (FLAG at
        ``rows`` as read by this run: FLAG changes only in :meth:`commit`, so it is still
        FLAG now), else read now.

        Where it does not, staging the flags would only have the commit find them equal:
        writing a staged flag column costs as much as writing an output column (0.3 s of
        CPU per 1.2 M rows of four correlations in 100-row tiles, measured), reading
        FLAG a fifth of that.  FLAG itself still changes only in :meth:`commit`.  With
        ``flag_read`` nothing is read (0.3 s of a 10^7-row run in time order, measured).
        """
        if flag_read is not None:
            return not np.array_equal(flag_read, new_flag)
        order = np.argsort(rows, kind="stable")
        with msio.MainTable(self.target_ms) as table:
            current = table.read_rows(["FLAG"], rows[order])["FLAG"]
        return not np.array_equal(current, np.asarray(new_flag)[order])

    def commit(self) -> None:
        """Make the finished run visible: FLAG backup, new FLAG, columns renamed.

        FLAG is backed up into FLAG_HITOPS_BACKUP the first time hitops changes it;
        the staged flags replace FLAG on the rows whose flags this run staged (block by
        block, only where they differ; a chunk whose new flags equalled FLAG staged
        none); each staging column takes its final name (an existing column of that
        name, kept until now, is removed first).
        """
        written, step = self.flags_staged, self.chunk_rows
        with tables.main_table(self.target_ms, writable=True) as t:
            t.lock(write=True)
            n_row = t.nrows()
            changed = []
            for start in range(0, n_row, step):
                n = min(step, n_row - start)
                rows = written[start:start + n]
                if not rows.any():
                    continue
                flag = t.getcol("FLAG", start, n)
                new = flag.copy()
                new[rows] = _staged_flags(t, start, rows)
                if not np.array_equal(new, flag):
                    changed.append(start)
            if changed and FLAG_BACKUP not in t.colnames():
                desc = t.getcoldesc("FLAG")
                desc["name"] = FLAG_BACKUP
                t.addcols(tables.column_description(FLAG_BACKUP, desc),
                          like_dminfo(t.getdminfo("FLAG"), FLAG_BACKUP, dm_names(t),
                                      fixed_shape=fixed_cell_shape(desc)))
                for start in range(0, n_row, step):
                    n = min(step, n_row - start)
                    t.putcol(FLAG_BACKUP, t.getcol("FLAG", start, n), start, n)
                self.backup_written = True
            for start in changed:
                n = min(step, n_row - start)
                rows = written[start:start + n]
                flag = t.getcol("FLAG", start, n)
                flag[rows] = _staged_flags(t, start, rows)
                t.putcol("FLAG", flag, start, n)
            self.flag_written = bool(changed)
            if STAGING_FLAG in t.colnames():
                t.removecols([STAGING_FLAG])
            for method, final in self.outputs.items():
                if final in t.colnames():
                    t.removecols([final])
                t.renamecol(self.staging[method], final)

    def rollback(self) -> None:
        """After a failure or an interrupt: drop the staging columns (nothing else changed)."""
        try:
            with tables.main_table(self.target_ms, writable=True) as t:
                t.lock(write=True)
                drop = [c for c in self.created if c in t.colnames()]
                if drop:
                    t.removecols(drop)
            if not drop:   # stopped before anything was written
                return
            log.error("calibrate stopped before it finished writing %s: removed its unfinished "
                      "columns; the set is as it was before this run", self.target_ms)
        except Exception as err:  # the original error matters more
            raise RollbackError(
                f"calibrate failed while writing {self.target_ms} and could not remove its "
                f"unfinished columns ({' '.join(str(err).split())}); they start with "
                f"{STAGING_PREFIX}: the next hitops calibrate run on the set removes them, or "
                "remove them by hand (casacore table.removecols)") from err


def _staged_flags(table, start: int, staged: np.ndarray) -> np.ndarray:
    """The staged flags of the rows ``start + i`` where ``staged[i]``: only rows whose flags
    were staged are read (in a column of variable cell shape, such as the one copied from
    casatools.simulator's FLAG, a cell never written has no value to read)."""
    return msio.rows_reader(table, start + np.flatnonzero(staged))(STAGING_FLAG)


def release_cluster_tables(client) -> None:
    """Let a cluster's scheduler and workers close their handles of the tables.

    The commit renames and removes columns; a process that still holds the table
    open from this run's reads would fail on its next use of it ("another process
    changed the number of columns").  dask-ms keeps its table handles only while
    tasks refer to them: wait until the scheduler has released this run's tasks,
    then collect the garbage everywhere (best effort: a failure here only means
    a later run on the same cluster reopens the table).
    """
    import gc

    def settle(dask_scheduler=None, timeout=5.0):
        deadline = time.monotonic() + timeout
        while dask_scheduler is not None and dask_scheduler.tasks and time.monotonic() < deadline:
            time.sleep(0.05)
        return gc.collect()

    try:
        client.run_on_scheduler(settle)
        client.run(gc.collect)
    except Exception as err:   # noqa: BLE001 - best effort, see above
        log.debug("could not ask the cluster to release its tables: %s", err)
