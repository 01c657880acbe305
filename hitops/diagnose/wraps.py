"""Reference-band wrap times, to mark on phase plots (the paper's second figure).

The reference Measurement Set's phase (``--ref-column``, DATA by default)
is read per baseline and correlation; a wrap is a step larger than pi
between consecutive usable samples, the same detector PWC uses
(:func:`hitops.tracking.count.count_wraps`).  Baselines are matched by
station names, so the two bands' ANTENNA tables may be ordered differently.  A
wideband reference is read as the vector average of all its channels (the phase
near its mean frequency: the troposphere's excess path makes every channel's phase
proportional to its frequency).
"""

from __future__ import annotations

import logging
from typing import Dict, List

import numpy as np

from ..tracking.count import count_wraps
from .read import GridData
from .spectral_read import read_band

log = logging.getLogger("hitops.diagnose")


def reference_wraps(ref_ms: str, target: GridData, ref_column: str = "DATA"
                    ) -> tuple[Dict[str, Dict[str, np.ndarray]], List[str]]:
    """Wrap times (MJD s) per target baseline name and correlation, plus warnings.

    A target correlation missing from the reference uses the reference's
    first parallel hand.
    """
    ref = read_band(ref_ms, [ref_column], correlations="all")
    warnings: List[str] = []
    ref_index = {}
    for b in range(ref.n_bl):
        a1, a2 = ref.antenna_names[ref.ant1[b]], ref.antenna_names[ref.ant2[b]]
        ref_index[(a1, a2)] = b
        ref_index[(a2, a1)] = b
    parallel = [i for i, n in enumerate(ref.corr_names) if n in ("RR", "LL", "XX", "YY", "I")]
    fallback = parallel[0] if parallel else 0
    phase_all = np.angle(ref.vis[ref_column])
    wraps: Dict[str, Dict[str, np.ndarray]] = {}
    missing: List[str] = []
    for b in range(target.n_bl):
        name = target.baseline_name(b)
        key = (target.antenna_names[target.ant1[b]], target.antenna_names[target.ant2[b]])
        rb = ref_index.get(key)
        if rb is None:
            missing.append(name)
            continue
        wraps[name] = {}
        for corr in target.corr_names:
            rc = ref.corr_names.index(corr) if corr in ref.corr_names else fallback
            valid = ~ref.flag[rb, :, rc]
            count = count_wraps(np.ascontiguousarray(phase_all[rb, :, rc]),
                                np.ascontiguousarray(valid))
            steps = np.flatnonzero(np.diff(count) != 0) + 1
            wraps[name][corr] = ref.times[steps]
    if missing:
        warnings.append(f"--ref-ms {ref_ms}: no reference rows for baseline(s) "
                        f"{', '.join(missing)}; no wrap markers there")
    return wraps, warnings
