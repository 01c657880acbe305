"""Which (field, spectral window) group of the reference band calibrates which of the target band.

A Measurement Set from a VLBI pipeline may hold several fields (sources,
calibrators) and several spectral windows (IFs).  dask-ms gives one dataset
per (FIELD_ID, DATA_DESC_ID) group (:func:`hitops.io.read.open_groups`); this
module pairs the two bands' groups:

* fields by name (FIELD::NAME), since the two sets may number them
  differently; a set with one field on each side pairs those whatever their
  names; a field in one band only is left out with a warning;
* within a field, spectral windows in frequency order (the lowest reference
  window with the lowest target window, and so on), or every target window
  with the one reference window when the reference band has one; any other
  count is refused, naming the windows;
* each pair has its own R = nu_target / nu_reference (mean channel frequency);
  with several channels each target channel gets its own R_k = nu_k / nu_reference
  (hitops/calibrate/channels.py).

Rows of one group never meet another's: each pair is matched, tracked and
transferred on its own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np

from ..errors import MeasurementSetError
from ..io.metadata import SetMetadata

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class BandGroup:
    """One (field, data description) group of one band, with what calibration needs of it."""

    key: Tuple[int, int]      # (FIELD_ID, DATA_DESC_ID)
    field: str                # FIELD::NAME
    spw: int                  # SPECTRAL_WINDOW_ID
    freq: float               # mean channel frequency (Hz)
    n_chan: int
    corr: Tuple[int, ...]     # CORR_TYPE of the group's polarisation setup
    chan_freq: Tuple[float, ...] = ()   # CHAN_FREQ (Hz), increasing


@dataclass(frozen=True)
class GroupPair:
    """A reference-band group and the target-band group it calibrates."""

    ref: BandGroup
    tgt: BandGroup

    @property
    def label(self) -> str:
        return f"field {self.tgt.field}, spectral windows {self.ref.spw} -> {self.tgt.spw}"


def describe_groups(meta: SetMetadata, keys, role: str) -> List[BandGroup]:
    """The :class:`BandGroup` of each (FIELD_ID, DATA_DESC_ID) key; channels checked."""
    ms, names = meta.ms, meta.fields.names
    groups = []
    for field_id, ddid in sorted(keys):
        if ddid >= len(meta.data_descriptions) or field_id >= max(len(names), 1):
            raise MeasurementSetError(
                f"{role} '{ms}': rows refer to DATA_DESC_ID {ddid} / FIELD_ID {field_id}, "
                "which the DATA_DESCRIPTION / FIELD tables do not hold; the set is damaged")
        spw = meta.window_of(ddid)
        window = meta.windows[spw]
        chan_freq = _channels(ms, role, spw, window.num_chan, window.chan_freq)
        freq = float(np.mean(chan_freq))
        corr = meta.corr_types_of(ddid)
        field = names[field_id] if len(names) else ""
        groups.append(BandGroup((field_id, ddid), field, spw, freq, window.num_chan, corr,
                                tuple(float(f) for f in chan_freq)))
    return groups


def _channels(ms: str, role: str, spw: int, n_chan: int, chan_freq) -> np.ndarray:
    """A window's CHAN_FREQ, checked: one frequency per channel, finite, strictly increasing."""
    freq = np.asarray(chan_freq, dtype=np.float64).ravel()
    if freq.size != n_chan:
        raise MeasurementSetError(
            f"{role} '{ms}': spectral window {spw} has NUM_CHAN {n_chan} but {freq.size} "
            "CHAN_FREQ values; the SPECTRAL_WINDOW table is damaged: rewrite it (CASA "
            "mstransform) or take the window out (CASA split spw=...)")
    if not np.isfinite(freq).all() or (freq.size > 1 and not (np.diff(freq) > 0).all()):
        order = "decreasing or repeated" if np.isfinite(freq).all() else "not finite"
        raise MeasurementSetError(
            f"{role} '{ms}': the channel frequencies of spectral window {spw} are {order} "
            f"({freq[0] / 1e9:.6g} .. {freq[-1] / 1e9:.6g} GHz); per-channel ratios need "
            "them strictly increasing: reverse the window (CASA mstransform "
            "regridms=True outframe='') or pass --average-channels")
    return freq


def pair_groups(ref_ms: str, target_ms: str, ref: List[BandGroup],
                tgt: List[BandGroup]) -> List[GroupPair]:
    """Pair the bands' groups: fields by name, spectral windows in frequency order."""
    if len(ref) == 1 and len(tgt) == 1:
        return [GroupPair(ref[0], tgt[0])]
    ref_fields = _by_field(ref, ref_ms)
    tgt_fields = _by_field(tgt, target_ms)
    if len(ref_fields) == 1 and len(tgt_fields) == 1:
        # one source on each side: its name may be spelt differently (M87 / M87*)
        pairs_of_fields = [(next(iter(ref_fields.values())), next(iter(tgt_fields.values())))]
    else:
        common = [f for f in tgt_fields if f in ref_fields]
        for name in sorted(set(ref_fields) ^ set(tgt_fields)):
            log.warning("field %s is in %s only: left out", name,
                        ref_ms if name in ref_fields else target_ms)
        if not common:
            raise MeasurementSetError(
                f"no field of {target_ms} ({', '.join(sorted(tgt_fields))}) is in {ref_ms} "
                f"({', '.join(sorted(ref_fields))}); fields are paired by FIELD::NAME: "
                "rename one band's field or split the sets to one field each")
        pairs_of_fields = [(ref_fields[f], tgt_fields[f]) for f in common]
    pairs = []
    for ref_groups, tgt_groups in pairs_of_fields:
        ref_groups = sorted(ref_groups, key=lambda g: g.freq)
        tgt_groups = sorted(tgt_groups, key=lambda g: g.freq)
        if len(ref_groups) == 1:
            pairs.extend(GroupPair(ref_groups[0], g) for g in tgt_groups)
        elif len(ref_groups) == len(tgt_groups):
            pairs.extend(GroupPair(r, t) for r, t in zip(ref_groups, tgt_groups))
        else:
            raise MeasurementSetError(
                f"field {tgt_groups[0].field}: {len(ref_groups)} spectral windows in {ref_ms} "
                f"({_windows(ref_groups)}) and {len(tgt_groups)} in {target_ms} "
                f"({_windows(tgt_groups)}); windows are paired in frequency order, so the "
                "counts must agree (or the reference band have one): split the sets "
                "(CASA split spw=...) so that they do")
    return pairs


def _by_field(groups: List[BandGroup], ms: str) -> Dict[str, List[BandGroup]]:
    """Groups by field name; two FIELD_IDs of one name cannot be told apart in the other band."""
    out: Dict[str, List[BandGroup]] = {}
    ids: Dict[str, set] = {}
    for g in groups:
        out.setdefault(g.field, []).append(g)
        ids.setdefault(g.field, set()).add(g.key[0])
    for name, field_ids in ids.items():
        if len(field_ids) > 1:
            raise MeasurementSetError(
                f"{ms}: {len(field_ids)} fields named {name!r} (FIELD_ID "
                f"{', '.join(str(i) for i in sorted(field_ids))}) hold data; fields are paired "
                "between the bands by name: rename them in the FIELD table or split the set "
                "(CASA split field=...)")
    return out


def _windows(groups: List[BandGroup]) -> str:
    return ", ".join(f"{g.spw} at {g.freq / 1e9:.6g} GHz" for g in groups)
