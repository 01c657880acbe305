"""Everything a calibrate run changes in a target processing set, in one transaction.

The MSv4 counterpart of :class:`hitops.calibrate.output.OutputTransaction`, with the
same methods the chunk loop and the commit call (``check_space``,
``create_columns``, ``write_chunk``, ``commit``, ``rollback``; the report reads
``flag_written`` and ``backup_written``).  Each method's result is a data group of
its own in every partition the run writes (hitops/io/msv4/data_group.py): its
correlated data and its own flags (the input's flags | not calibrated, as the MSv2
run writes into FLAG), the weight and UVW shared with the group the target was read
from.  So the input's VISIBILITY and FLAG are never written and no flag backup is
made; the groups are staged before the first chunk, written chunk by chunk, and
registered in ``data_groups`` only at :meth:`commit` (a failure or an interrupt
before then removes the staged arrays: the store as it was).  The output column
names map to group names as hitops/io/msv4/columns.py says (PWC_DATA -> ``pwc``).
"""

from __future__ import annotations

import logging
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..errors import InputError, RollbackError
from ..io import access
from ..io.msv4.columns import BASE_GROUP, group_of_column
from ..io.msv4.data_group import DataGroupWriter, consolidate_partition
from ..io.msv4.group_rows import PartitionSource, rows_by_source
from ..io.msv4.store import is_processing_set
from ..kernels.wideband import rotate_channels
from .output import OutputTransaction

log = logging.getLogger("hitops.calibrate")

#: what the names of the staged groups start with (:attr:`DataGroupTransaction.staging`)
STAGED = "staged:"


class DataGroupTransaction:
    """This run's new data groups in the target processing set: staged, written, registered.

    ``outputs``: method -> output column (its data group: ``group_of_column``);
    ``sources``: the target's groups the run reads (each a partition's rows of one field;
    their ROWIDs are the rows :meth:`write_chunk` is given); ``chunk_rows``: rows per
    chunk, so the new arrays are stored in chunks of about one run chunk's time steps.
    """

    #: the writes go to new zarr arrays that no read of the run touches: on a thread of
    #: their own, beside the next chunk's read (hitops/calibrate/chunk_io.py)
    writes_apart = True

    def __init__(self, target_ps: str, outputs: Dict[str, str], target_column: str,
                 sources: List[PartitionSource], chunk_rows: int, overwrite: bool):
        self.target_ms = target_ps
        self.outputs = dict(outputs)
        self.data_groups = {m: group_of_column(c) for m, c in outputs.items()}
        self.like = group_of_column(target_column)
        for method, name in self.data_groups.items():
            if name in (self.like, BASE_GROUP):
                raise InputError(f"output column {outputs[method]} of {target_ps} names data "
                                 f"group '{name}', the input's; choose another --output-column "
                                 "(e.g. PWC_DATA)")
        self.sources = sorted(sources, key=lambda s: s.row_base)
        self.row_bases = np.array([s.row_base for s in self.sources], np.int64)
        n_rows = max((s.row_base + s.n_rows for s in self.sources), default=0)
        self.rows_written = np.zeros(n_rows, dtype=bool)
        self.flags_staged = self.rows_written      # every written row has its own flags
        self.backup_written = False                # the input's FLAG is never written
        self.flag_written = False
        partitions = sorted({s.partition for s in self.sources})
        step = {s.partition: s.reader(s.group).time_step(chunk_rows) for s in self.sources}
        # made (and checked: name, taken, writable) before anything is written
        self.writers = {(p, m): DataGroupWriter(target_ps, p, name, like=self.like,
                                                overwrite=overwrite, time_chunk=step[p],
                                                description=f"hitops calibrate --method {m} "
                                                f"from data group '{self.like}'")
                        for p in partitions for m, name in self.data_groups.items()}
        self.staged: List[DataGroupWriter] = []

    def check_space(self) -> None:
        """Refuse before writing when the new groups could not fit uncompressed."""
        readers = {s.partition: s.reader(s.group) for s in self.sources}
        n_cells = len(self.data_groups) * sum(
            r.n_time * r.n_baseline * int(np.prod(r.cell_shape("DATA"))) for r in readers.values())
        # complex64 data and one byte of flag per cell and method (zarr compresses: less)
        access.require_free_space(self.target_ms, 9 * n_cells,
                                  f"data groups {', '.join(self.data_groups.values())}")

    def create_columns(self, scattered: bool = False) -> List[str]:
        """Stage every new group's arrays (``scattered`` is the MSv2 tiling's concern)."""
        # --overwrite: the old groups unregistered first, said once per partition (two
        # consolidations, each about 0.02 s at 10^6 rows), before any array is staged
        dropped = {p for (p, _), w in self.writers.items()
                   if w.unregister_existing(consolidate=False)}
        for partition in sorted(dropped):
            consolidate_partition(self.target_ms, partition)
        for writer in self.writers.values():
            self.staged.append(writer)
            writer.stage()
        return [f"{p}/{w.variables.correlated_data}" for (p, _), w in self.writers.items()]

    def write_chunk(self, rows: np.ndarray, data: np.ndarray, phasors: Dict[str, np.ndarray],
                    new_flag: np.ndarray, scheduler=None,
                    delays: Optional[Dict[str, np.ndarray]] = None,
                    chan_offset: Optional[np.ndarray] = None,
                    flag_read: Optional[np.ndarray] = None) -> None:
        """One chunk's outputs (data times each method's phasor, as the MSv2 transaction
        computes them) and new flags into their cells of each method's group."""
        if delays is None:
            out = {m: (data * p[:, None, :]).astype(np.complex64, copy=False)
                   for m, p in phasors.items()}
        else:
            out = {m: rotate_channels(data, p, delays[m], chan_offset) for m, p in phasors.items()}
        self.write_outputs(rows, out, new_flag)

    def write_outputs(self, rows: np.ndarray, outputs: Dict[str, np.ndarray],
                      new_flag: np.ndarray, scheduler=None,
                      flag_read: Optional[np.ndarray] = None) -> None:
        """One chunk's finished outputs (method -> (n, n_chan, n_corr), corrected already:
        the ``--reference-table`` path's) and new flags into their cells of each method's
        group (``scheduler`` and ``flag_read`` are the MSv2 transaction's concerns)."""
        out = {m: np.asarray(v).astype(np.complex64, copy=False) for m, v in outputs.items()}
        rows = np.asarray(rows, np.int64)
        which = np.searchsorted(self.row_bases, rows, side="right") - 1
        # a chunk's rows are one group's (a run's chunk never spans two): no sort
        one = which.size == 0 or which.min() == which.max()
        for k in (which[:1] if one else np.unique(which)):
            source = self.sources[k]
            sel = np.arange(rows.size) if one else np.flatnonzero(which == k)
            times, baselines = source.cells((rows if one else rows[sel]) - source.row_base)
            # a partition of one field: its steps follow each other, one run
            runs = _runs_of_steps(times) if source.several_fields else [np.arange(times.size)]
            for run in runs:
                whole = run.size == rows.size      # one group, one run: no copies
                cells = slice(None) if whole else sel[run]
                t_run, b_run = (times, baselines) if whole else (times[run], baselines[run])
                span = (int(t_run.min()), int(t_run.max()) + 1)
                for method, values in out.items():
                    self.writers[(source.partition, method)].write_cells(
                        span, t_run, b_run, values[cells], new_flag[cells])
        if self.rows_written is not None:   # None: a worker's copy (see __getstate__)
            self.rows_written[rows] = True

    def __getstate__(self) -> Dict:
        """A copy for a dask worker (hitops/calibrate/worker_chunks.py) leaves the
        per-row record of written rows behind (a byte per row of the store): the client
        keeps it (:meth:`mark_written`)."""
        state = dict(vars(self))
        state["rows_written"] = state["flags_staged"] = None
        return state

    def zarr_chunks(self, partition: str, first_step: int, last_step: int) -> List[Tuple[str, int]]:
        """(partition, time chunk index) of the staged arrays' chunks that time steps
        ``first_step``..``last_step`` of ``partition`` fall in: two writes sharing one must
        not run at once (zarr reads, changes and writes a chunk back whole)."""
        step = next(int(w.time_chunk) for (p, _), w in self.writers.items() if p == partition)
        return [(partition, c) for c in range(first_step // step, last_step // step + 1)]

    def mark_written(self, source: PartitionSource) -> None:
        """Every row of ``source`` written (by the chunk tasks of a cluster's workers, which
        write their own copies of this transaction: hitops/calibrate/worker_chunks.py)."""
        self.rows_written[source.row_base:source.row_base + source.n_rows] = True

    @property
    def staging(self) -> Dict[str, str]:
        """method -> the name its staged group is read back and rewritten by (the
        calibrator step's, hitops/calibrate/set_rows.py)."""
        return {m: f"{STAGED}{g}" for m, g in self.data_groups.items()}

    def _cells(self, rows: np.ndarray):
        """(partition, indices into ``rows``, time indices, baselines) per group of the
        ascending ROWIDs ``rows``."""
        for source, sel, positions in rows_by_source(self.sources, rows):
            times, baselines = source.cells(positions)
            yield source.partition, sel, times, baselines

    def read_staged(self, rows: np.ndarray, name: str) -> np.ndarray:
        """(n, n_chan, n_corr) what the run has written at ``rows`` into the staged group
        named ``name`` (one of :attr:`staging`)."""
        method = next(m for m, n in self.staging.items() if n == name)
        return self._read(rows, method, 0)

    def _read(self, rows: np.ndarray, method: str, which: int) -> np.ndarray:
        rows = np.asarray(rows, np.int64)
        parts = [self.writers[(p, method)].read_cells(t, b)[which]
                 for p, _, t, b in self._cells(rows)]
        if not parts:
            return self.writers[next(iter(self.writers))].read_cells(
                np.zeros(0, np.int64), np.zeros(0, np.int64))[which]
        return np.concatenate(parts) if len(parts) > 1 else parts[0]

    def flags_now(self, set_rows, rows: np.ndarray) -> np.ndarray:
        """(n, n_chan, n_corr) the flags the run has given ``rows`` so far: every written
        row has them staged, the same in each method's group (``set_rows`` is the MSv2
        transaction's concern)."""
        return self._read(rows, next(iter(self.data_groups)), 1)

    def restage(self, rows: np.ndarray, outputs: Dict[str, np.ndarray],
                new_flag: Optional[np.ndarray] = None) -> None:
        """Staged groups (by their :attr:`staging` names) rewritten at ``rows`` by a later
        step of the same run (``--calibrator-field``); new flags, when given, go to every
        method's group, as an MSv2 run's one FLAG holds them for every column."""
        method_of = {n: m for m, n in self.staging.items()}
        for partition, sel, times, baselines in self._cells(np.asarray(rows, np.int64)):
            for name, values in outputs.items():
                self.writers[(partition, method_of[name])].rewrite_cells(
                    times, baselines, data=np.asarray(values)[sel].astype(np.complex64))
            if new_flag is not None:
                for method in self.data_groups:
                    self.writers[(partition, method)].rewrite_cells(
                        times, baselines, flag=np.asarray(new_flag)[sel])

    def commit(self) -> None:
        """Register every new group (each partition's data_groups, then its and the root's
        consolidated metadata, last)."""
        for writer in self.staged:
            writer.commit(consolidate=False)
        for partition in sorted({p for p, _ in self.writers}):
            consolidate_partition(self.target_ms, partition)
        self.staged = []

    def rollback(self) -> None:
        """After a failure or an interrupt: remove the staged arrays (nothing else changed)."""
        if not self.staged:
            return
        try:
            for writer in self.staged:
                writer.abort()
            self.staged = []
            log.error("calibrate stopped before it finished writing %s: removed its unfinished "
                      "data groups; the store is as it was before this run", self.target_ms)
        except Exception as err:  # the original error matters more
            raise RollbackError(
                f"calibrate failed while writing {self.target_ms} and could not remove its "
                f"unfinished arrays ({' '.join(str(err).split())}); they are in no data group, "
                "so no reader takes them for a result, and the next hitops calibrate run "
                "writing the same group removes them") from err


def _runs_of_steps(times: np.ndarray) -> List[np.ndarray]:
    """Indices of ``times`` by runs of consecutive time steps: a partition holding several
    fields interleaves their steps, and each write covers only this group's own."""
    steps = np.unique(times)
    breaks = np.flatnonzero(np.diff(steps) > 1) + 1
    if breaks.size == 0:
        return [np.arange(times.size)]
    run_of_step = np.zeros(steps.size, np.int64)
    run_of_step[breaks] = 1
    run = np.cumsum(run_of_step)[np.searchsorted(steps, times)]
    return [np.flatnonzero(run == r) for r in range(int(run.max()) + 1)]


def transaction_class(target: str) -> type:
    """The transaction of a run that writes to ``target``: :class:`DataGroupTransaction` for
    a processing set, :class:`~hitops.calibrate.output.OutputTransaction` for a Measurement
    Set v2.  Its ``writes_apart`` says where the writes run (hitops/calibrate/chunk_io.py),
    and so what the memory budget counts (hitops/calibrate/memory.py): the one place that
    decides both."""
    return DataGroupTransaction if is_processing_set(target) else OutputTransaction


def data_groups_entry(tx) -> Optional[Dict]:
    """The report's ``data_groups``: each method's group and the partitions it is in, for a
    run that wrote a processing set (None for a Measurement Set v2's transaction)."""
    if not isinstance(tx, DataGroupTransaction):
        return None
    partitions = sorted({s.partition for s in tx.sources})
    return {m: {"data_group": g, "partitions": partitions} for m, g in tx.data_groups.items()}
