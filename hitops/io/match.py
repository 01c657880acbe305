"""Matching the rows of a reference-band and a target-band Measurement Set.

Rows are matched by time (within a tolerance, by default half the smallest
INTERVAL of either band), by station pair (station codes from
:mod:`hitops.io.stations`, through an antenna map for stations whose names
differ between bands, e.g. the paper's JCMT at 86 GHz paired with SMA at
230 GHz) and by correlation type
(POLARIZATION::CORR_TYPE), never by row order or position.  A reference row
whose antenna order is reversed with respect to the target baseline is
conjugated, which also exchanges its cross-hand correlations (RL <-> LR).

:class:`hitops.calibrate.chunks.GroupMatch` puts both bands on one
(baseline, time) grid, chunk by chunk, from the pieces here: baselines are the
target's, times the union of both bands' times.
"""

from __future__ import annotations

import logging
from typing import Dict, List, Mapping, Sequence

import numpy as np

from ..errors import StationError
from .ms_create import CORR_NAMES
from .stations import SAME_STATION_M, Stations

log = logging.getLogger("hitops")


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


def pair_antennas(ref: Stations, tgt: Stations, antenna_map: Mapping[str, str],
                  tgt_ant1: np.ndarray, tgt_ant2: np.ndarray) -> np.ndarray:
    """Target antenna index of each reference antenna (-1 when it has none).

    Stations are paired by code (:mod:`hitops.io.stations`), or through
    ``antenna_map`` for stations named differently in the two bands.
    ``tgt_ant1``/``tgt_ant2``: the target band's baselines.  A target station
    with no partner is left out (its baselines are flagged) with one warning
    naming it and its baselines; a pair of stations whose positions are more
    than 1 km apart, a map entry naming an unknown station, or no baseline in
    common is a :class:`StationError`.
    """
    tgt_index = {code: i for i, code in enumerate(tgt.codes)}
    for ref_code, tgt_code in antenna_map.items():
        if ref_code not in ref.codes:
            raise StationError(f"--antenna-map {ref_code}={tgt_code}: reference station "
                               f"{ref_code} is not in {ref.ms} (stations: {', '.join(ref.codes)})")
        if tgt_code not in tgt_index:
            raise StationError(f"--antenna-map {ref_code}={tgt_code}: target station "
                               f"{tgt_code} is not in {tgt.ms} (stations: {', '.join(tgt.codes)})")
    ref_to_tgt = np.full(ref.n_ant, -1, dtype=np.int64)
    for i, code in enumerate(ref.codes):
        ref_to_tgt[i] = tgt_index.get(antenna_map.get(code, code), -1)
    mapped = ref_to_tgt[ref_to_tgt >= 0]
    if np.unique(mapped).size != mapped.size:
        raise StationError("two reference stations map to the same target station; "
                           f"check --antenna-map and the ANTENNA tables of {ref.ms} and {tgt.ms}")
    if ref.positions is not None and tgt.positions is not None:
        for i in np.flatnonzero(ref_to_tgt >= 0):
            j = ref_to_tgt[i]
            distance = float(np.linalg.norm(ref.positions[i] - tgt.positions[j]))
            if ref.codes[i] in antenna_map:
                log.info("station %s of %s paired with %s of %s by --antenna-map: %.0f m apart",
                         ref.codes[i], ref.ms, tgt.codes[j], tgt.ms, distance)
            elif distance > SAME_STATION_M:
                raise StationError(
                    f"station {ref.codes[i]} of {ref.ms} and station {tgt.codes[j]} of {tgt.ms} "
                    f"share a code but are {distance / 1e3:.1f} km apart (ANTENNA::POSITION); "
                    "they are not the same station: fix the ANTENNA table, or pair stations "
                    "on purpose with --antenna-map REF=TARGET")
    paired = set(mapped.tolist())
    n_ant_t = tgt.n_ant
    used = np.flatnonzero(np.bincount(tgt_ant1, minlength=n_ant_t)
                          + np.bincount(tgt_ant2, minlength=n_ant_t))
    orphans = [a for a in used if a not in paired]
    both = np.array([a in paired and b in paired for a, b in zip(tgt_ant1, tgt_ant2)], bool)
    if not both.any():
        raise StationError(
            f"no baseline of {tgt.ms} has both stations in {ref.ms} (target stations "
            f"{', '.join(tgt.codes)}; reference stations {', '.join(ref.codes)}); nothing can be "
            "calibrated: check that the sets are the two bands of one observation, or pair "
            "stations named differently with --antenna-map REF=TARGET")
    for a in orphans:
        names = [f"{tgt.codes[p]}-{tgt.codes[q]}" for p, q in zip(tgt_ant1, tgt_ant2)
                 if a in (p, q)]
        log.warning("target station %s of %s is not in %s: its %d baseline(s) %s have no "
                    "reference and are left out (flagged in the output); pair it with "
                    "--antenna-map REF=%s if it is named differently there", tgt.codes[a], tgt.ms,
                    ref.ms, len(names), ", ".join(names[:8]) + (" ..." if len(names) > 8 else ""),
                    tgt.codes[a])
    return ref_to_tgt


def pairing_table(ref: Stations, tgt: Stations, ref_to_tgt: np.ndarray) -> List[Dict]:
    """One entry per station of either band: how it was paired (for the log and report)."""
    rows = []
    for i, code in enumerate(ref.codes):
        j = int(ref_to_tgt[i])
        rows.append({"reference": code, "reference_antenna": i,
                     "target": tgt.codes[j] if j >= 0 else None,
                     "target_antenna": j if j >= 0 else None})
    for j in sorted(set(range(tgt.n_ant)) - set(int(x) for x in ref_to_tgt if x >= 0)):
        rows.append({"reference": None, "reference_antenna": None, "target": tgt.codes[j],
                     "target_antenna": j})
    return rows


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
