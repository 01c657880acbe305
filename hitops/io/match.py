"""Matching the rows of a reference-band and a target-band Measurement Set.

Rows are matched by time (within a tolerance, by default half the smallest
INTERVAL of either band), by station pair (ANTENNA::NAME, through an
antenna map for stations whose names differ between bands, e.g. the paper's
JCMT at 86 GHz paired with SMA at 230 GHz) and by correlation type
(POLARIZATION::CORR_TYPE), never by row order or position.  A reference row
whose antenna order is reversed with respect to the target baseline is
conjugated, which also exchanges its cross-hand correlations (RL <-> LR).

:class:`hitops.calibrate.chunks.ChunkMatch` puts both bands on one
(baseline, time) grid, chunk by chunk, from the pieces here: baselines are the
target's, times the union of both bands' times.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Mapping, Sequence

import numpy as np

from ..errors import StationError
from .ms_create import CORR_NAMES


@dataclass
class BandRows:
    """Per-row metadata of one band (storage order)."""

    ms: str
    time: np.ndarray
    ant1: np.ndarray
    ant2: np.ndarray
    scan: np.ndarray
    interval: np.ndarray
    antenna_names: List[str]
    corr_types: List[int]

    @property
    def n_row(self) -> int:
        return self.time.size


def parse_antenna_map(text: str | Mapping[str, str] | None) -> Dict[str, str]:
    """``"JC=SM,AA=AP"`` -> {"JC": "SM", "AA": "AP"} (reference name -> target name)."""
    from ..errors import InputError

    if not text:
        return {}
    if isinstance(text, Mapping):
        return {str(k): str(v) for k, v in text.items()}
    mapping = {}
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        if item.count("=") != 1 or not all(p.strip() for p in item.split("=")):
            raise InputError(f"--antenna-map entry '{item}' is not REF=TARGET "
                             "(e.g. --antenna-map JC=SM)")
        ref, tgt = (p.strip() for p in item.split("="))
        if ref in mapping:
            raise InputError(f"--antenna-map names reference station {ref} twice")
        mapping[ref] = tgt
    return mapping


def pair_antennas(ref: BandRows, tgt: BandRows, antenna_map: Mapping[str, str]) -> np.ndarray:
    """Target antenna index of each reference antenna (-1 when it has none).

    Raises :class:`StationError` when a map entry names an unknown station or
    a target station used in the data has no reference counterpart.
    """
    tgt_index = {name: i for i, name in enumerate(tgt.antenna_names)}
    for ref_name, tgt_name in antenna_map.items():
        if ref_name not in ref.antenna_names:
            raise StationError(f"--antenna-map {ref_name}={tgt_name}: reference station "
                               f"{ref_name} is not in {ref.ms} (stations: "
                               f"{', '.join(ref.antenna_names)})")
        if tgt_name not in tgt_index:
            raise StationError(f"--antenna-map {ref_name}={tgt_name}: target station "
                               f"{tgt_name} is not in {tgt.ms} (stations: "
                               f"{', '.join(tgt.antenna_names)})")
    ref_to_tgt = np.full(len(ref.antenna_names), -1, dtype=np.int64)
    for i, name in enumerate(ref.antenna_names):
        ref_to_tgt[i] = tgt_index.get(antenna_map.get(name, name), -1)
    mapped = ref_to_tgt[ref_to_tgt >= 0]
    if np.unique(mapped).size != mapped.size:
        raise StationError("two reference stations map to the same target station; "
                           "check --antenna-map and the ANTENNA tables of "
                           f"{ref.ms} and {tgt.ms}")
    # stations used by the target rows: counts over the few antenna indices (no sort)
    n_ant_t = len(tgt.antenna_names)
    used_tgt = np.flatnonzero(np.bincount(tgt.ant1, minlength=n_ant_t)
                              + np.bincount(tgt.ant2, minlength=n_ant_t))
    paired = set(mapped.tolist())
    orphans = [tgt.antenna_names[a] for a in used_tgt if a not in paired]
    if orphans:
        unused_ref = [n for i, n in enumerate(ref.antenna_names) if ref_to_tgt[i] < 0]
        raise StationError(
            f"target station(s) {', '.join(orphans)} of {tgt.ms} have no counterpart in "
            f"{ref.ms} (unpaired reference stations: {', '.join(unused_ref) or 'none'}); "
            "pair them with --antenna-map REF=TARGET (e.g. --antenna-map JC=SM)")
    return ref_to_tgt


def correlation_map(ref_types: Sequence[int], tgt_types: Sequence[int]) -> np.ndarray:
    """(2, n_corr) reference correlation index of each target correlation (-1: none).

    Row 0 for rows in the same antenna order, row 1 for swapped rows, whose
    conjugate exchanges the hands (RL of p-q is the conjugate of LR of q-p).
    """
    ref_index = {int(code): i for i, code in enumerate(ref_types)}
    name_code = {name: code for code, name in CORR_NAMES.items()}
    out = np.full((2, len(tgt_types)), -1, dtype=np.int64)
    for c, code in enumerate(tgt_types):
        out[0, c] = ref_index.get(int(code), -1)
        name = CORR_NAMES.get(int(code))
        swapped_code = name_code.get(name[::-1]) if name else int(code)
        out[1, c] = ref_index.get(int(swapped_code), -1)
    return out


def distinct_counts(values: np.ndarray):
    """(sorted distinct values, rows holding each), like np.unique(return_counts=True).

    Columns stored as a few ascending runs (time-ordered or baseline-major
    sets) take one linear numba pass (hitops.kernels.sorted_runs); shuffled
    columns, whose runs are short, take the sort.
    """
    from ..kernels.sorted_runs import count_runs, run_distinct_counts

    values = np.ascontiguousarray(values)
    n_runs = count_runs(values)
    if values.size == 0 or n_runs > 64:
        distinct, counts = np.unique(values, return_counts=True)
        return distinct, counts.astype(np.int64)
    distinct, counts, extra = run_distinct_counts(values)
    if extra.size:   # later runs hold values the first one lacks: merge the few extra ones
        more, more_counts = np.unique(extra, return_counts=True)
        merged, inverse = np.unique(np.concatenate([distinct, more]), return_inverse=True)
        counts = np.bincount(inverse, weights=np.concatenate([counts, more_counts]),
                             minlength=merged.size).astype(np.int64)
        distinct = merged
    return distinct, counts


def distinct_ints(values: np.ndarray) -> np.ndarray:
    """Sorted distinct values of small non-negative integers (SCAN_NUMBER) without a sort."""
    values = np.asarray(values)
    if values.size and values.min() >= 0 and values.max() < 10_000_000:
        return np.flatnonzero(np.bincount(values))
    return np.unique(values)
