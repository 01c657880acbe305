"""A new data group written into a partition whole or not at all: :class:`DataGroupWriter`.

MSv4 keeps a result beside its input: a data group (the partition's ``data_groups``
attribute) names its own correlated data and flag variables and shares the
weight, UVW and field_and_source of the group it was made from.  So nothing of
the input is written: its ``VISIBILITY`` and ``FLAG`` stay as they were and no
flag backup is needed.

Whole or nothing, in the order xradio's readers see it:

1. **stage**: the group's arrays (``VISIBILITY_<NAME>``, ``FLAG_<NAME>``) are created
   with the input's shape, chunks and codecs, NaN and flagged where nothing is written,
   and marked ``hitops_data_group: <name>``; they are in no data group and not in
   the consolidated metadata, so no reader takes them for a result;
2. **write**: the rows of each chunk (:class:`~hitops.io.msv4.rows.PartitionRows`) go
   to their (time, baseline) cells, a time range per call;
3. **commit**: the partition's ``data_groups`` gets the new entry, then the
   partition's and the root's consolidated metadata are written again (last).

A failure before the commit removes the staged arrays (:meth:`DataGroupWriter.abort`);
arrays left by a killed run (marked, unregistered) are removed by the next writer of
that name.  An existing group is refused unless ``overwrite``: then it is
unregistered first (so an interrupted overwrite leaves no group, never a half-new one).
"""

from __future__ import annotations

import datetime
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ...errors import OutputExistsError, ProcessingSetError
from .rows import PartitionRows
from .store import open_store, quiet_zarr, zarr_group

#: the attribute that marks an array as written by this writer (stale when unregistered)
MARK = "hitops_data_group"
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class GroupVariables:
    """The variable names of a new data group."""

    name: str
    correlated_data: str
    flag: str

    @classmethod
    def of(cls, name: str) -> "GroupVariables":
        return cls(name=name, correlated_data=f"VISIBILITY_{name.upper()}",
                   flag=f"FLAG_{name.upper()}")


class DataGroupWriter:
    """Writes data group ``name`` of ``partition``, made like group ``like``."""

    def __init__(self, store_path: str, partition: str, name: str, like: str = "base",
                 overwrite: bool = False, description: str = "",
                 time_chunk: Optional[int] = None):
        self.store = open_store(store_path, role="output")
        self.entry = self.store.partition(partition)
        self.like = self.entry.group(like)
        self.variables = GroupVariables.of(name)
        self.overwrite = overwrite
        #: time steps per zarr chunk of the new arrays (default: the input's); a caller writing
        #: chunk by chunk gives PartitionReader.time_step, so every write is whole chunks
        self.time_chunk = time_chunk
        self.description = description or f"written by hitops from data group '{like}'"
        self._check(name)
        self._staged = None     # the new arrays (correlated data, flag) once staged
        self._unregistered = False

    def _check(self, name: str) -> None:
        where = f"'{self.store.path}' partition '{self.entry.name}'"
        if not _NAME.match(name):
            raise ProcessingSetError(f"data group name '{name}' for {where}: use lower-case "
                                     "letters, digits and '_', starting with a letter")
        try:   # a probe, not os.access: it also sees a read-only file system (and root)
            tempfile.TemporaryFile(dir=Path(self.store.path) / self.entry.name).close()
        except OSError as err:
            raise ProcessingSetError(f"{where} is not writable ({err.strerror}); give a "
                                     "writable copy of the store") from None
        taken = [g.name for g in self.entry.data_groups]
        if name in taken and not self.overwrite:
            raise OutputExistsError(f"{where} already has data group '{name}'; give another "
                                    "name, or --overwrite to replace it")
        others = {v for g in self.entry.data_groups if g.name != name
                  for v in (g.correlated_data, g.flag, g.weight, g.uvw)}
        for variable in (self.variables.correlated_data, self.variables.flag):
            if variable in others:
                raise ProcessingSetError(f"{where}: {variable} belongs to another data group; "
                                         f"name the new group other than '{name}'")
            path = Path(self.store.path) / self.entry.name / variable
            if path.exists() and name not in taken and self._mark_of(variable) != name:
                raise ProcessingSetError(f"{where} holds an array {variable} that no data group "
                                         "names and hitops did not write; remove it or choose "
                                         "another group name")

    def _group(self):
        return zarr_group(self.store.path, mode="r+", path=self.entry.name, use_consolidated=False)

    def _mark_of(self, variable: str):
        try:
            return self._group()[variable].attrs.get(MARK)
        except KeyError:
            return None

    def unregister_existing(self, consolidate: bool = True) -> bool:
        """Take an existing group of the name out of ``data_groups`` (``overwrite``); whether
        there was one.  ``consolidate`` False: the caller then consolidates the metadata once
        for several groups of the partition (:func:`consolidate_partition`), before any of
        them stages its arrays (which must not be in the consolidated metadata)."""
        if self._unregistered or self.variables.name not in [g.name for g in
                                                             self.entry.data_groups]:
            return False
        self._register(drop=True, consolidate=consolidate)
        self._unregistered = True
        return True

    def stage(self) -> None:
        """Create the group's arrays (an existing group of the name unregistered first)."""
        self.unregister_existing()
        group = self._group()
        for variable in (self.variables.correlated_data, self.variables.flag):
            shutil.rmtree(Path(self.store.path) / self.entry.name / variable, ignore_errors=True)
        made = []
        for variable, like, fill in ((self.variables.correlated_data, self.like.correlated_data,
                                      complex(np.nan, np.nan)),
                                     (self.variables.flag, self.like.flag, True)):
            source = group[like]
            attributes = dict(source.attrs)
            attributes[MARK] = self.variables.name
            chunks = source.chunks if self.time_chunk is None else \
                (min(int(self.time_chunk), source.shape[0]),) + tuple(source.chunks[1:])
            made.append(group.create_array(variable, shape=source.shape, dtype=source.dtype,
                                           chunks=chunks, compressors=source.compressors,
                                           fill_value=fill, attributes=attributes,
                                           dimension_names=source.metadata.dimension_names))
        # the arrays themselves, kept: looking one up in the group reads its metadata
        # again (about 1.4 ms a write, 0.8 s of a 10^7-row run's three groups)
        self._staged = tuple(made)

    def write(self, rows: PartitionRows, data: np.ndarray, flag: np.ndarray) -> None:
        """The rows' data (n_row, n_chan, n_corr) and flags into their cells; the chunk's other
        cells stay NaN and flagged."""
        self.write_cells(rows.time_slice, rows.time_index, rows.baseline, data, flag)

    def write_cells(self, time_slice, time_index: np.ndarray, baseline: np.ndarray,
                    data: np.ndarray, flag: np.ndarray) -> None:
        """:meth:`write` of rows given by their cells: the time steps ``time_slice`` [start,
        stop) are written whole, the cells (time_index, baseline) from ``data`` and ``flag``,
        every other cell of those steps NaN and flagged."""
        if self._staged is None:
            raise RuntimeError("DataGroupWriter.write before stage()")
        start, stop = time_slice
        out, flag_out = self._staged
        shape = (stop - start,) + out.shape[1:]
        cell = np.asarray(time_index, np.int64) * shape[1] + np.asarray(baseline, np.int64)
        if cell.size == shape[0] * shape[1] and (cell.size == 0 or (
                cell[0] == start * shape[1] and np.all(np.diff(cell) == 1))):
            # every cell of the steps, in grid order: the rows are the block (no fill)
            block = np.asarray(data, out.dtype).reshape(shape)
            flags = np.asarray(flag, bool).reshape(shape)
        else:
            block = np.full(shape, np.nan + 0j, out.dtype)
            flags = np.ones(shape, bool)
            block[time_index - start, baseline] = data
            flags[time_index - start, baseline] = flag
        out[start:stop] = block
        flag_out[start:stop] = flags

    def read_cells(self, time_index: np.ndarray, baseline: np.ndarray):
        """(data, flag) the staged arrays hold at the cells (time_index, baseline), each
        (n, n_chan, n_corr): what this run has written there so far (the calibrator step
        reads its transfer's output back, hitops/calibrate/phaseref)."""
        out, flag_out = self._arrays()
        time_index = np.asarray(time_index, np.int64)
        if time_index.size == 0:
            return (np.zeros((0,) + out.shape[2:], out.dtype),
                    np.zeros((0,) + flag_out.shape[2:], bool))
        start, stop = int(time_index.min()), int(time_index.max()) + 1
        rel = time_index - start
        return out[start:stop][rel, baseline], flag_out[start:stop][rel, baseline]

    def rewrite_cells(self, time_index: np.ndarray, baseline: np.ndarray,
                      data: Optional[np.ndarray] = None,
                      flag: Optional[np.ndarray] = None) -> None:
        """Cells written before given new ``data`` and/or ``flag``; every other cell of
        their time steps kept as it is (a later step of the same run: the calibrator's)."""
        time_index = np.asarray(time_index, np.int64)
        if time_index.size == 0:
            return
        start, stop = int(time_index.min()), int(time_index.max()) + 1
        rel = time_index - start
        for array, values in zip(self._arrays(), (data, flag)):
            if values is None:
                continue
            block = array[start:stop]
            block[rel, baseline] = values
            array[start:stop] = block

    def _arrays(self):
        if self._staged is None:
            raise RuntimeError("DataGroupWriter: cells read or rewritten before stage()")
        return self._staged

    def commit(self, consolidate: bool = True) -> None:
        """Register the group in ``data_groups``, then the consolidated metadata (last;
        ``consolidate`` False: the caller does that once for several groups, :func:`consolidate`)."""
        self._register(drop=False, consolidate=consolidate)
        self._staged = None

    def abort(self) -> None:
        """Remove the staged arrays (the partition as it was)."""
        for variable in (self.variables.correlated_data, self.variables.flag):
            shutil.rmtree(Path(self.store.path) / self.entry.name / variable, ignore_errors=True)
        self._staged = None

    def _register(self, drop: bool, consolidate: bool = True) -> None:
        group = self._group()
        groups = {k: dict(v) for k, v in dict(group.attrs["data_groups"]).items()}
        groups.pop(self.variables.name, None)
        if not drop:
            base = groups[self.like.name]
            groups[self.variables.name] = {
                "correlated_data": self.variables.correlated_data, "flag": self.variables.flag,
                "weight": base.get("weight"), "uvw": base.get("uvw"),
                "field_and_source": base.get("field_and_source"),
                "description": self.description,
                "date": datetime.datetime.now(datetime.timezone.utc).isoformat()}
        group.attrs["data_groups"] = groups
        if consolidate:
            consolidate_partition(self.store.path, self.entry.name)

    def __enter__(self) -> "DataGroupWriter":
        self.stage()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def consolidate_partition(store_path: str, partition: str) -> None:
    """The partition's consolidated metadata, then the root's, written again (what readers
    see; xradio's order: the root last)."""
    import zarr   # zarr_group has imported it (or said how to install it)

    with quiet_zarr():
        zarr.consolidate_metadata(store_path, path=partition)
        zarr.consolidate_metadata(store_path)
