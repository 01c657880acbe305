"""What a path holds: an MSv4 processing set in zarr v3, checked before anything reads it.

xradio (1.3) writes a processing set as one zarr v3 group per partition under a root
group.  It writes the root's attribute ``type: processing_set`` and the root's
consolidated metadata last, after every partition (its
``convert_msv2_to_processing_set``), and a partition's own consolidated metadata
after the partition's last value (its ``stream_write`` module).  So these files
say whether a store is whole, without zarr and without reading any data:

* ``<path>/zarr.json``: a zarr v3 group; ``attributes.type == "processing_set"``
  makes it a processing set (:func:`is_processing_set`, the format test of
  :func:`hitops.io.metadata.read_metadata`);
* ``<path>/<partition>/zarr.json``: ``attributes.type == "visibility"``,
  ``schema_version`` (this reader: 4.0.x) and ``data_groups`` (which variables
  belong together), and its ``consolidated_metadata``.

:func:`open_store` checks all of it and returns the typed :class:`ProcessingSetStore`;
bad input is one :class:`~hitops.errors.ProcessingSetError` line naming the store,
the partition and the remedy.
"""

from __future__ import annotations

import json
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

from ...errors import ProcessingSetError

PROCESSING_SET_TYPE = "processing_set"
#: partitions of interferometer data (xradio's single-dish partitions are type "spectrum")
VISIBILITY_TYPE = "visibility"
#: the schema versions read here: major and minor (xradio 1.3 writes 4.0.1)
SUPPORTED_SCHEMA = (4, 0)


@dataclass(frozen=True)
class DataGroup:
    """One entry of a partition's ``data_groups``: the variables that belong together."""

    name: str
    correlated_data: str            # e.g. VISIBILITY, VISIBILITY_CORRECTED
    flag: str
    weight: Optional[str]
    uvw: Optional[str]
    field_and_source: Optional[str]  # the partition's child group of its fields
    description: str = ""


@dataclass(frozen=True)
class PartitionEntry:
    """A partition as its zarr.json describes it (no values read)."""

    name: str
    schema_version: str
    data_groups: Tuple[DataGroup, ...]
    arrays: Tuple[str, ...]         # the partition's arrays, from its consolidated metadata

    def group(self, name: str) -> DataGroup:
        for group in self.data_groups:
            if group.name == name:
                return group
        raise ProcessingSetError(
            f"partition '{self.name}' has no data group '{name}' (it has "
            f"{', '.join(g.name for g in self.data_groups)}); name one of those")


@dataclass(frozen=True)
class ProcessingSetStore:
    """A processing set checked whole: its path and its partitions in name order."""

    path: str
    partitions: Tuple[PartitionEntry, ...]

    def partition(self, name: str) -> PartitionEntry:
        for entry in self.partitions:
            if entry.name == name:
                return entry
        raise ProcessingSetError(
            f"'{self.path}' has no partition '{name}' (it has "
            f"{', '.join(p.name for p in self.partitions)})")


@contextmanager
def quiet_zarr():
    """zarr 3.1 warns on every open of xradio's stores that consolidated metadata and
    fixed-length strings are not in the zarr v3 specification yet; xradio's own readers
    rely on both, so the warning says nothing to a hitops user."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Zarr V3 specification")
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
        yield


def zarr_group(store: str, mode: str = "r", **kwargs):
    """A zarr group of the store (the msv4 extra's zarr, imported here)."""
    try:
        import zarr
    except ImportError:
        raise ProcessingSetError(
            f"'{store}' is a zarr store: reading MSv4 processing sets needs the msv4 extra "
            "(pip install 'hitops[msv4]', or make setup)") from None

    with quiet_zarr():
        return zarr.open_group(store, mode=mode, **kwargs)


def _read_json(path: Path) -> Optional[dict]:
    """The JSON document at ``path``; None when it is missing or not whole."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def is_zarr_store(path) -> bool:
    """True when ``path`` is a zarr group (v3 ``zarr.json`` or v2 ``.zgroup``)."""
    p = Path(path)
    return (p / "zarr.json").is_file() or (p / ".zgroup").is_file()


def is_processing_set(path) -> bool:
    """True when ``path`` is a zarr v3 group whose root says ``type: processing_set``."""
    root = _read_json(Path(path) / "zarr.json")
    return bool(root) and (root.get("attributes") or {}).get("type") == PROCESSING_SET_TYPE


def open_store(path, role: str = "input") -> ProcessingSetStore:
    """The checked :class:`ProcessingSetStore` at ``path``, or one line saying what is wrong."""
    p = Path(str(path).rstrip("/"))
    root = _read_json(p / "zarr.json")
    if root is None:
        if (p / ".zgroup").is_file():
            raise ProcessingSetError(
                f"{role} '{p}' is a zarr v2 store; hitops reads MSv4 processing sets in zarr v3 "
                "(as xradio >= 1.0 writes them): convert the Measurement Set again with xradio")
        raise ProcessingSetError(f"{role} '{p}' is not a zarr store (no readable zarr.json)")
    on_disk = sorted(c.name for c in p.iterdir() if (c / "zarr.json").is_file())
    if (root.get("attributes") or {}).get("type") != PROCESSING_SET_TYPE:
        if any("schema_version" in ((_read_json(p / c / "zarr.json") or {}).get("attributes") or {})
               for c in on_disk):
            raise ProcessingSetError(
                f"{role} '{p}' holds partitions but its root has no type 'processing_set', which "
                "xradio writes last: its conversion did not finish; remove it and convert again")
        raise ProcessingSetError(
            f"{role} '{p}' is a zarr store but not an MSv4 processing set (its root has no "
            "attribute type='processing_set'); give a store written by xradio")
    listed = _consolidated_children(root)
    if listed is None:
        raise ProcessingSetError(
            f"{role} '{p}' has no consolidated metadata at its root (written last): a write "
            "into it did not finish; convert it again")
    partitions = []
    for name in on_disk:
        attrs = ((_read_json(p / name / "zarr.json") or {}).get("attributes") or {})
        if attrs.get("type") != VISIBILITY_TYPE:
            continue
        if name not in listed:
            raise ProcessingSetError(
                f"{role} '{p}': partition '{name}' is not in the store's consolidated metadata: "
                "its write did not finish; convert the set again")
        partitions.append(_partition(p, name, role))
    if not partitions:
        raise ProcessingSetError(f"{role} '{p}' holds no visibility partition; nothing to read")
    return ProcessingSetStore(path=str(p), partitions=tuple(partitions))


def _consolidated_children(group_json: dict) -> Optional[dict]:
    """{name: metadata} of a group's consolidated metadata; None when it has none."""
    consolidated = group_json.get("consolidated_metadata")
    if not isinstance(consolidated, dict) or not isinstance(consolidated.get("metadata"), dict):
        return None
    return consolidated["metadata"]


def _partition(p: Path, name: str, role: str) -> PartitionEntry:
    doc = _read_json(p / name / "zarr.json") or {}
    attrs = doc.get("attributes") or {}
    version = str(attrs.get("schema_version", ""))
    if tuple(_version_numbers(version)[:2]) != SUPPORTED_SCHEMA:
        raise ProcessingSetError(
            f"{role} '{p}': partition '{name}' has schema_version '{version}'; hitops reads "
            f"MSv4 schema {SUPPORTED_SCHEMA[0]}.{SUPPORTED_SCHEMA[1]}.x (xradio 1.3): convert "
            "the Measurement Set again with xradio 1.3")
    children = _consolidated_children(doc)
    if children is None:
        raise ProcessingSetError(
            f"{role} '{p}': partition '{name}' has no consolidated metadata (xradio writes it "
            "after the partition's last value): its write did not finish; convert it again")
    arrays = tuple(sorted(k for k, v in children.items()
                          if "/" not in k and (v or {}).get("node_type") == "array"))
    groups = _data_groups(p, name, attrs.get("data_groups"), role)
    for group in groups:
        for variable in (group.correlated_data, group.flag):
            if variable not in arrays:
                raise ProcessingSetError(
                    f"{role} '{p}': partition '{name}' names {variable} in data group "
                    f"'{group.name}' but holds no such array: the store is damaged or "
                    "half-written; convert it again")
    return PartitionEntry(name=name, schema_version=version, data_groups=groups, arrays=arrays)


def _data_groups(p: Path, name: str, raw, role: str) -> Tuple[DataGroup, ...]:
    if not isinstance(raw, dict) or not raw:
        raise ProcessingSetError(
            f"{role} '{p}': partition '{name}' has no data_groups attribute; give a "
            "processing set written by xradio")
    groups = []
    for group_name, entry in raw.items():
        entry = entry if isinstance(entry, dict) else {}
        if not entry.get("correlated_data") or not entry.get("flag"):
            raise ProcessingSetError(
                f"{role} '{p}': partition '{name}', data group '{group_name}' names no "
                "correlated_data or no flag variable; the store is damaged")
        groups.append(DataGroup(name=str(group_name), correlated_data=entry["correlated_data"],
                                flag=entry["flag"], weight=entry.get("weight"),
                                uvw=entry.get("uvw"),
                                field_and_source=entry.get("field_and_source"),
                                description=str(entry.get("description", ""))))
    return tuple(groups)


def _version_numbers(version: str) -> Tuple[int, ...]:
    numbers = []
    for part in version.split("."):
        if not part.isdigit():
            break
        numbers.append(int(part))
    return tuple(numbers)
