"""A processing set's metadata, read once: :class:`ProcessingSetLayout`.

The MSv4 keeps no MSv2 ids; this module recovers them where xradio (1.3) keeps them
and rebuilds the rest in a documented order (docs/msv4.md "What the metadata
reader recovers"):

* windows: the ``frequency`` coordinate of each partition (``CHAN_FREQ``), its
  ``reference_frequency`` and ``channel_width`` attributes; xradio names a window
  ``<NAME>_<SPECTRAL_WINDOW_ID>`` (or ``spw_<id>``), so the id is the name's last
  ``_`` part; windows without one follow in frequency order;
* fields: the ``field_name`` of the base data group's field_and_source dataset,
  ``<NAME>_<FIELD_ID>`` likewise;
* polarization setups: the ``polarization`` coordinate (Stokes names -> casacore
  codes) with the receptors of ``antenna_xds.polarization_type``; in order of
  the windows that use them;
* data descriptions: the distinct (window, polarization) pairs in that order:
  the MSv2 order whenever DATA_DESC_ID follows SPECTRAL_WINDOW_ID, as it does in
  sets written by CASA's simulator, importuvfits and hitops;
* antennas: each partition's ``antenna_xds`` (the antennas its baselines use, in
  ANTENNA id order), merged keeping that order.  An antenna without rows in any
  partition is not in the processing set.

Only small coordinate arrays are read (zarr, through the consolidated metadata).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ...errors import ProcessingSetError
from .store import PartitionEntry, ProcessingSetStore, quiet_zarr, zarr_group

#: casacore's Stokes codes (casacore/measures/Measures/Stokes.h) of the names MSv4 stores
STOKES_CODES = {"I": 1, "Q": 2, "U": 3, "V": 4, "RR": 5, "RL": 6, "LR": 7, "LL": 8,
                "XX": 9, "XY": 10, "YX": 11, "YY": 12}


@dataclass(frozen=True, eq=False)
class AntennaTable:
    names: Tuple[str, ...]          # ANTENNA::NAME as the MSv2 had it
    stations: Tuple[str, ...]
    positions: np.ndarray           # (n_ant, 3) ITRF metres
    dish_diameters: np.ndarray      # (n_ant,) metres
    mounts: Tuple[str, ...]
    v4_names: Tuple[str, ...]       # antenna_name as the partitions name them (baselines)


@dataclass(frozen=True, eq=False)
class FieldTable:
    names: Tuple[str, ...]          # FIELD::NAME (xradio's "_<id>" suffix taken off)
    phase_dirs: np.ndarray          # (n_field, 2) radians
    v4_names: Tuple[str, ...]       # field_name as the partitions name them


@dataclass(frozen=True, eq=False)
class SpectralWindow:
    v4_name: str
    chan_freq: np.ndarray           # (n_chan,) Hz, as the partition's frequency coordinate
    chan_width: np.ndarray          # (n_chan,) Hz: the one width MSv4 keeps, per channel
    ref_frequency: float


@dataclass(frozen=True)
class CorrelationSetup:
    corr_types: Tuple[int, ...]                 # casacore Stokes codes
    receptors: Tuple[Tuple[int, int], ...]      # (ANTENNA1's, ANTENNA2's) receptor index


@dataclass(frozen=True)
class PartitionLayout:
    """A partition's place among the recovered ids."""

    name: str
    data_desc_id: int
    window: int
    polarization: int
    # field_name of the partition's own field_and_source dataset: the fields its times
    # hold (xradio builds both from the partition's FIELD_IDs, conversion.py)
    field_v4_names: Tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class ProcessingSetLayout:
    store: ProcessingSetStore
    antennas: AntennaTable
    fields: FieldTable
    windows: Tuple[SpectralWindow, ...]
    polarizations: Tuple[CorrelationSetup, ...]
    data_descriptions: Tuple[Tuple[int, int], ...]  # (window, polarization) per DATA_DESC_ID
    partitions: Tuple[PartitionLayout, ...]

    def partition(self, name: str) -> PartitionLayout:
        self.store.partition(name)                   # one line naming the partitions there are
        return next(p for p in self.partitions if p.name == name)


@dataclass(frozen=True, eq=False)
class _PartitionFacts:
    """What one partition says, before the ids are recovered across partitions."""

    entry: PartitionEntry
    window: SpectralWindow
    correlations: CorrelationSetup
    antennas: AntennaTable
    fields: FieldTable


def split_id(v4_name: str) -> Tuple[str, Optional[int]]:
    """('NAME', id) of xradio's '<NAME>_<id>'; (name, None) without a numeric suffix."""
    head, sep, tail = v4_name.rpartition("_")
    return (head, int(tail)) if sep and tail.isdigit() else (v4_name, None)


def read_layout(store: ProcessingSetStore) -> ProcessingSetLayout:
    """The :class:`ProcessingSetLayout` of a checked store (small arrays only)."""
    root = zarr_group(store.path)
    with quiet_zarr():
        facts = [_partition_facts(root, entry, store.path) for entry in store.partitions]
    window_ids = _window_ids(facts)
    windows = [None] * (max(window_ids.values()) + 1)
    for fact in facts:
        windows[window_ids[fact.window.v4_name]] = fact.window
    if any(w is None for w in windows):
        windows = [w for w in windows if w is not None]          # ids with no data: packed
        window_ids = {w.v4_name: i for i, w in enumerate(windows)}
    setups: List[CorrelationSetup] = []
    pairs: List[Tuple[int, int]] = []
    for fact in sorted(facts, key=lambda f: window_ids[f.window.v4_name]):
        if fact.correlations not in setups:
            setups.append(fact.correlations)
        pair = (window_ids[fact.window.v4_name], setups.index(fact.correlations))
        if pair not in pairs:
            pairs.append(pair)
    pairs.sort()
    partitions = []
    for fact in facts:
        pair = (window_ids[fact.window.v4_name], setups.index(fact.correlations))
        partitions.append(PartitionLayout(name=fact.entry.name, data_desc_id=pairs.index(pair),
                                          window=pair[0], polarization=pair[1],
                                          field_v4_names=fact.fields.v4_names))
    return ProcessingSetLayout(store=store, antennas=_merge_antennas([f.antennas for f in facts]),
                               fields=_merge_fields([f.fields for f in facts]),
                               windows=tuple(windows), polarizations=tuple(setups),
                               data_descriptions=tuple(pairs), partitions=tuple(partitions))


def _strings(array) -> Tuple[str, ...]:
    return tuple(str(v) for v in np.asarray(array[...]).ravel())


def _attr_value(attrs, key: str) -> Optional[float]:
    value = attrs.get(key)
    if isinstance(value, dict):
        value = value.get("data")
    return None if value is None else float(np.asarray(value).ravel()[0])


def _partition_facts(root, entry: PartitionEntry, path: str) -> _PartitionFacts:
    group = root[entry.name]
    freq = group["frequency"]
    chan_freq = np.asarray(freq[...], np.float64)
    width = _attr_value(freq.attrs, "channel_width")
    ref = _attr_value(freq.attrs, "reference_frequency")
    window = SpectralWindow(
        v4_name=str(freq.attrs.get("spectral_window_name", f"{entry.name}_window")),
        chan_freq=chan_freq,
        chan_width=np.full(chan_freq.size, np.nan if width is None else width),
        ref_frequency=float(chan_freq[0]) if ref is None else ref)
    antennas = _antennas(group["antenna_xds"])
    corr_names = _strings(group["polarization"])
    unknown = [c for c in corr_names if c not in STOKES_CODES]
    if unknown:
        raise ProcessingSetError(f"'{path}': partition '{entry.name}' has correlations "
                                 f"{unknown} that are not Stokes names hitops knows")
    receptor_types = _receptor_types(group["antenna_xds"], corr_names)
    correlations = CorrelationSetup(
        corr_types=tuple(STOKES_CODES[c] for c in corr_names),
        receptors=tuple(_receptor_pair(c, receptor_types) for c in corr_names))
    base = entry.group("base") if "base" in [g.name for g in entry.data_groups] \
        else entry.data_groups[0]
    fields_group = group[base.field_and_source or "field_and_source_base_xds"]
    v4_fields = _strings(fields_group["field_name"])
    dirs = np.asarray(fields_group["FIELD_PHASE_CENTER_DIRECTION"][...], np.float64)
    fields = FieldTable(names=tuple(split_id(n)[0] for n in v4_fields),
                        phase_dirs=dirs.reshape(-1, dirs.shape[-1])[:len(v4_fields), :2],
                        v4_names=v4_fields)
    return _PartitionFacts(entry=entry, window=window, correlations=correlations,
                           antennas=antennas, fields=fields)


def _antennas(group) -> AntennaTable:
    v4_names = _strings(group["antenna_name"])
    stations = _strings(group["station_name"]) if "station_name" in group else ("",) * len(v4_names)
    names = v4_names
    if group.attrs.get("relocatable_antennas"):
        # xradio names ALMA/VLA/NOEMA antennas '<NAME>_<STATION>' (create_antenna_xds)
        names = tuple(n[:-len(s) - 1] if s and n.endswith("_" + s) else n
                      for n, s in zip(v4_names, stations))
    return AntennaTable(
        names=names, stations=stations, v4_names=v4_names,
        positions=np.asarray(group["ANTENNA_POSITION"][...], np.float64).reshape(-1, 3),
        dish_diameters=np.asarray(group["ANTENNA_DISH_DIAMETER"][...], np.float64),
        mounts=_strings(group["mount"]) if "mount" in group else ("",) * len(v4_names))


def _receptor_types(group, corr_names: Sequence[str]) -> Tuple[str, ...]:
    """The receptor types in receptor order (the first antenna's; 'R','L' or 'X','Y')."""
    if "polarization_type" in group:
        types = np.asarray(group["polarization_type"][...])
        if types.size:
            return tuple(str(t) for t in types.reshape(types.shape[0], -1)[0])
    return tuple(dict.fromkeys(ch for name in corr_names for ch in name if len(name) == 2))


def _receptor_pair(corr_name: str, receptor_types: Tuple[str, ...]) -> Tuple[int, int]:
    if len(corr_name) != 2 or any(c not in receptor_types for c in corr_name):
        return (0, 0)                                  # Stokes I, Q, U, V: no receptor pair
    return (receptor_types.index(corr_name[0]), receptor_types.index(corr_name[1]))


def _window_ids(facts: Sequence[_PartitionFacts]) -> Dict[str, int]:
    """{window v4 name: SPECTRAL_WINDOW_ID}: the name's suffix, else after them by frequency."""
    ids: Dict[str, int] = {}
    for fact in facts:
        ids.setdefault(fact.window.v4_name, split_id(fact.window.v4_name)[1])
    known = [i for i in ids.values() if i is not None]
    if len(set(known)) != len(known):
        known = []                                      # not xradio's suffixes: none trusted
        ids = {name: None for name in ids}
    unnamed = sorted((n for n, i in ids.items() if i is None),
                     key=lambda n: next(float(f.window.chan_freq[0]) for f in facts
                                        if f.window.v4_name == n))
    start = max(known) + 1 if known else 0
    ids.update({name: start + k for k, name in enumerate(unnamed)})
    return ids


def _merge_order(lists: Sequence[Sequence[str]]) -> List[str]:
    """One order of the names keeping the order of each list (each a subsequence of the
    MSv2's id order): a name goes before every name it preceded in some list."""
    order: List[str] = []
    for names in lists:
        position = 0
        for name in names:
            if name in order:
                position = max(position, order.index(name) + 1)
            else:
                order.insert(position, name)
                position += 1
    return order


def _merge_antennas(tables: Sequence[AntennaTable]) -> AntennaTable:
    order = _merge_order([t.v4_names for t in tables])
    where = {}
    for table in tables:
        for i, name in enumerate(table.v4_names):
            where.setdefault(name, (table, i))
    rows = [where[name] for name in order]
    return AntennaTable(
        names=tuple(t.names[i] for t, i in rows), stations=tuple(t.stations[i] for t, i in rows),
        positions=np.array([t.positions[i] for t, i in rows], np.float64).reshape(-1, 3),
        dish_diameters=np.array([t.dish_diameters[i] for t, i in rows], np.float64),
        mounts=tuple(t.mounts[i] for t, i in rows), v4_names=tuple(order))


def _merge_fields(tables: Sequence[FieldTable]) -> FieldTable:
    found: Dict[str, Tuple[FieldTable, int]] = {}
    for table in tables:
        for i, name in enumerate(table.v4_names):
            found.setdefault(name, (table, i))
    ids = {name: split_id(name)[1] for name in found}
    numbered = all(i is not None for i in ids.values()) and len(set(ids.values())) == len(ids)
    order = sorted(found, key=lambda n: ids[n]) if numbered else list(found)
    return FieldTable(names=tuple(found[n][0].names[found[n][1]] for n in order),
                      phase_dirs=np.array([found[n][0].phase_dirs[found[n][1]] for n in order],
                                          np.float64).reshape(-1, 2),
                      v4_names=tuple(order))
