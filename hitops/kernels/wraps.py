"""TO DELETE after the switch (issue 12): the names hitops/calibrate/transfer.py still imports.

The wrap counter is :mod:`hitops.tracking.count` now; the rebuilt transfer
calls :class:`hitops.tracking.count.CountTracker` (or ``count_scans``) instead
of looking a tracker up by name.
"""

from __future__ import annotations

from ..errors import InputError
from ..tracking.count import count_wraps, wrap_events  # noqa: F401  (transfer.py)

#: the one tracker transfer.py looks up by name
TRACKERS = {"count": count_wraps}


def get_tracker(name: str):
    """The per-series tracker ``name`` (only 'count' runs inside the transfer tasks)."""
    if name not in TRACKERS:
        raise InputError(f"unknown wrap tracker '{name}'; known: {', '.join(sorted(TRACKERS))}")
    return TRACKERS[name]
