"""A partition's rows, chunk by chunk, in the shape hitops's Measurement Set readers give.

An MSv4 partition stores a dense (time, baseline_id) grid; a Measurement Set v2
stores rows.  :class:`PartitionReader` gives the grid back as rows: the cells
that hold an integration (``EFFECTIVE_INTEGRATION_TIME`` finite: xradio writes NaN
where the MSv2 had no row), in time order and, within a time, in baseline_id
order, with TIME in MSv2 seconds (MJD seconds: MSv4's Unix seconds plus
:data:`UNIX_TO_MJD_S`), ANTENNA1/2 as indices into the set's
:class:`~hitops.io.metadata.SetMetadata` antennas, DATA_DESC_ID, FIELD_ID and
SCAN_NUMBER as hitops/io/msv4/layout.py recovers them, and only the variables
asked for (:data:`VARIABLES`), read for whole time steps through zarr.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Iterator, Optional, Sequence, Tuple

import numpy as np

from ...errors import ProcessingSetError
from .layout import ProcessingSetLayout
from .store import quiet_zarr, zarr_group

#: seconds from the MJD epoch (1858-11-17, MSv2 TIME) to the Unix epoch (MSv4 time)
UNIX_TO_MJD_S = 40587 * 86400.0
#: what a chunk may hold beside the row metadata, by the data group's role
VARIABLES = ("DATA", "FLAG", "WEIGHT", "UVW")
#: where the presence of a cell is read, in order of preference (xradio writes NaN where
#: the MSv2 had no row); a partition with neither has every cell present
_PRESENCE = ("EFFECTIVE_INTEGRATION_TIME", "TIME_CENTROID")


@dataclass(frozen=True, eq=False)
class PartitionRows:
    """One chunk of a partition: rows of the time steps ``time_slice``, as MSv2 columns."""

    time_slice: Tuple[int, int]     # [start, stop) of the partition's time axis
    time_index: np.ndarray          # (n_row,) int64: each row's place on the time axis
    baseline: np.ndarray            # (n_row,) int64: each row's baseline_id
    time: np.ndarray                # (n_row,) float64, MSv2 seconds
    antenna1: np.ndarray            # (n_row,) int32, into SetMetadata.antennas
    antenna2: np.ndarray
    data_desc_id: np.ndarray        # (n_row,) int32
    field_id: np.ndarray            # (n_row,) int32
    scan_number: np.ndarray         # (n_row,) int32
    data: Optional[np.ndarray] = None     # (n_row, n_chan, n_corr) the group's correlated data
    flag: Optional[np.ndarray] = None     # (n_row, n_chan, n_corr) bool, the group's flag
    weight: Optional[np.ndarray] = None   # (n_row, n_chan, n_corr)
    uvw: Optional[np.ndarray] = None      # (n_row, 3)

    @property
    def n_row(self) -> int:
        return int(self.time.size)


class PartitionReader:
    """Rows of one partition and data group of a processing set (zarr, read only)."""

    def __init__(self, layout: ProcessingSetLayout, partition: str, data_group: str = "base"):
        self.layout = layout
        self.entry = layout.store.partition(partition)
        self.group = self.entry.group(data_group)
        self.place = layout.partition(partition)
        # each zarr array opened once: zarr parses an array's metadata on every lookup
        # (0.3 s of a 10^7-row run's reads went there)
        self._arrays: Dict[str, object] = {}
        with quiet_zarr():
            self._zarr = zarr_group(layout.store.path)[partition]
            self.times = np.asarray(self._array("time")[...], np.float64) + UNIX_TO_MJD_S
            self._ant1 = self._antenna_index("baseline_antenna1_name")
            self._ant2 = self._antenna_index("baseline_antenna2_name")
        self._field: Optional[np.ndarray] = None    # read on first use (row counts need
        self._scan: Optional[np.ndarray] = None     # neither: hitops.io.read.row_count)
        self._presence = next((v for v in _PRESENCE if v in self.entry.arrays), None)

    def _array(self, name: str):
        """The partition's zarr array ``name``, opened on first use."""
        if name not in self._arrays:
            with quiet_zarr():
                self._arrays[name] = self._zarr[name]
        return self._arrays[name]

    @property
    def scan_numbers(self) -> np.ndarray:
        """(n_time,) int32: SCAN_NUMBER of each time step."""
        if self._scan is None:
            with quiet_zarr():
                self._scan = _per_time(self._array("scan_name"), _scan_number)
        return self._scan

    @property
    def n_time(self) -> int:
        return int(self.times.size)

    @property
    def baseline_antennas(self) -> Tuple[np.ndarray, np.ndarray]:
        """(ANTENNA1, ANTENNA2) of each baseline_id, (n_baseline,) int32 each."""
        return self._ant1, self._ant2

    @property
    def n_baseline(self) -> int:
        return int(self._ant1.size)

    @property
    def field_ids(self) -> np.ndarray:
        """(n_time,) int32: FIELD_ID of each time step (a partition may hold several fields)."""
        if self._field is None:
            known = {name: i for i, name in enumerate(self.layout.fields.v4_names)}
            if len(self.place.field_v4_names) == 1:
                # a partition of one field (xradio's field_and_source dataset lists the
                # fields its times hold): its times are that field, and the per-time names
                # (27 characters each: 0.1 s per band at 357,150 steps) need no read
                self._field = np.full(self.n_time, known[self.place.field_v4_names[0]],
                                      np.int32)
            else:
                with quiet_zarr():
                    self._field = _per_time(self._array("field_name"), lambda n: known[n])
        return self._field

    @property
    def integration_time(self) -> float:
        """The time coordinate's ``integration_time`` in seconds (MSv2 INTERVAL); 0 if none."""
        value = self._array("time").attrs.get("integration_time", {})
        return float(value.get("data", 0.0)) if isinstance(value, dict) else 0.0

    def present(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, n_baseline) bool: which cells of time steps [start, stop) are rows."""
        if self._presence is None:
            return np.ones((stop - start, self.n_baseline), bool)
        return np.isfinite(self._read(self._presence, start, stop))

    def time_step(self, rows_per_chunk: int) -> int:
        """Time steps per chunk of about ``rows_per_chunk`` grid cells (at least one): also the
        time chunk a :class:`~hitops.io.msv4.DataGroupWriter` should store, so that a write
        of these chunks is whole zarr chunks (no read-modify-write)."""
        return max(1, int(rows_per_chunk) // max(1, self.n_baseline))

    def time_slices(self, rows_per_chunk: int) -> Tuple[Tuple[int, int], ...]:
        """[start, stop) time ranges of about ``rows_per_chunk`` grid cells, whole time steps."""
        step = self.time_step(rows_per_chunk)
        return tuple((t, min(t + step, self.n_time)) for t in range(0, self.n_time, step))

    def slice_of(self, t_lo: float, t_hi: float) -> Tuple[int, int]:
        """The time steps with ``t_lo <= TIME < t_hi`` (MSv2 seconds)."""
        return (int(np.searchsorted(self.times, t_lo, "left")),
                int(np.searchsorted(self.times, t_hi, "left")))

    def read(self, time_slice: Tuple[int, int], variables: Sequence[str] = ("DATA", "FLAG"),
             every_cell: bool = False) -> PartitionRows:
        """The rows of ``time_slice`` with the ``variables`` asked for (names of VARIABLES).
        ``every_cell``: the caller knows every cell of these steps is a row (its row counts
        per step, hitops/io/msv4/group_rows.py), so the presence array is not read again."""
        unknown = [v for v in variables if v not in VARIABLES]
        if unknown:
            raise ProcessingSetError(f"cannot read {unknown} of partition '{self.entry.name}'; "
                                     f"hitops reads {', '.join(VARIABLES)}")
        start, stop = time_slice
        if every_cell:
            present = None
            dense = True
            t_idx = np.repeat(np.arange(start, stop, dtype=np.int64), self.n_baseline)
            bl = np.tile(np.arange(self.n_baseline, dtype=np.int64), stop - start)
        else:
            present = self.present(start, stop)
            t_idx, bl = np.nonzero(present)
            t_idx = t_idx.astype(np.int64) + start
            bl = bl.astype(np.int64)
            dense = bool(present.all())     # every cell a row: a reshape, no gather (no copy)
        arrays = {v.lower(): _rows_of(self._variable(v, start, stop), present, dense)
                  for v in variables}
        return PartitionRows(
            time_slice=(start, stop), time_index=t_idx, baseline=bl, time=self.times[t_idx],
            antenna1=self._ant1[bl], antenna2=self._ant2[bl],
            data_desc_id=np.full(t_idx.size, self.place.data_desc_id, np.int32),
            field_id=self.field_ids[t_idx], scan_number=self.scan_numbers[t_idx], **arrays)

    def chunks(self, rows_per_chunk: int, variables: Sequence[str] = ("DATA", "FLAG"),
               t_lo: float = -np.inf, t_hi: float = np.inf) -> Iterator[PartitionRows]:
        """The rows with ``t_lo <= TIME < t_hi``, chunk by chunk (whole time steps)."""
        first, last = self.slice_of(t_lo, t_hi)
        for start, stop in self.time_slices(rows_per_chunk):
            start, stop = max(start, first), min(stop, last)
            if start < stop:
                yield self.read((start, stop), variables)

    def cell_shape(self, role: str) -> Tuple[int, ...]:
        """The shape of one row's cell of a variable (DATA: (n_chan, n_corr)), read from its
        metadata alone."""
        return tuple(int(n) for n in self._array(self._name_of(role)).shape[2:])

    def _name_of(self, role: str) -> str:
        name = {"DATA": self.group.correlated_data, "FLAG": self.group.flag,
                "WEIGHT": self.group.weight, "UVW": self.group.uvw}[role]
        if not name or name not in self.entry.arrays:
            raise ProcessingSetError(
                f"'{self.layout.store.path}': partition '{self.entry.name}', data group "
                f"'{self.group.name}' has no {role} variable; read it without {role}")
        return name

    def _variable(self, role: str, start: int, stop: int) -> np.ndarray:
        return self._read(self._name_of(role), start, stop)

    def _read(self, name: str, start: int, stop: int) -> np.ndarray:
        """Time steps [start, stop) of variable ``name``; a chunk zarr cannot decode is one
        line naming the variable and the steps."""
        try:
            with quiet_zarr():
                return np.asarray(self._array(name)[start:stop])
        except Exception as err:   # zarr's and the codecs' own errors (blosc: RuntimeError)
            raise ProcessingSetError(
                f"'{self.layout.store.path}': partition '{self.entry.name}', {name} of time "
                f"steps {start}-{stop - 1} cannot be read ({' '.join(str(err).split())}); the "
                "store is damaged: convert the Measurement Set again") from err

    def _antenna_index(self, coordinate: str) -> np.ndarray:
        names = [str(n) for n in np.asarray(self._array(coordinate)[...]).ravel()]
        known = {name: i for i, name in enumerate(self.layout.antennas.v4_names)}
        return np.array([known[n] for n in names], np.int32)


def _rows_of(grid: np.ndarray, present: np.ndarray, dense: bool) -> np.ndarray:
    """The (time, baseline, ...) grid's present cells as rows, in time then baseline order."""
    return grid.reshape((-1,) + grid.shape[2:]) if dense else grid[present]


def _per_time(names, number_of) -> np.ndarray:
    """(n_time,) int32: ``number_of(name)`` of each time step's name, one call per run of
    equal names (a scan or field lasts many steps: 357,143 steps sorted as strings took
    0.2 s, their runs take 0.02 s)."""
    values = np.asarray(names[...]).ravel()
    # zarr gives xradio's names as fixed-width text already: converting them again
    # copied them (0.08 s per 357,143 names)
    if values.dtype.kind != "U":
        values = values.astype(str)
    if values.size == 0:
        return np.zeros(0, np.int32)
    starts = np.concatenate([[0], np.flatnonzero(values[1:] != values[:-1]) + 1])
    known: Dict[str, int] = {}
    numbers = np.array([known.setdefault(str(values[i]), number_of(str(values[i])))
                        for i in starts], np.int32)
    return np.repeat(numbers, np.diff(np.concatenate([starts, [values.size]])))


def _scan_number(scan_name: str) -> int:
    """SCAN_NUMBER of xradio's scan_name (the MSv2 number as text); -1 when it is no number."""
    text = scan_name.strip()
    return int(text) if text.lstrip("-").isdigit() else -1
