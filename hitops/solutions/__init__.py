"""Solution-space FPT: a reference band's CASA calibration table in, a target-band table out.

``read`` (CASA tables -> typed series), ``wraps`` (numba wrap counting with rate
bridging and reference-antenna re-referencing), ``transfer`` (per-antenna,
per-target-channel transfer), ``write`` (the target Fringe Jones table), ``api``
(:func:`transfer_table`).  See docs/solutions.md.
"""

from .api import TransferReport, transfer_table

__all__ = ["TransferReport", "transfer_table"]
