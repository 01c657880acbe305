"""``hitops diagnose``: coherence metrics, ranked baseline tables and diagnostic plots.

``read`` (MS columns onto a (baseline, time) grid), ``metrics`` (C(T), tau_c),
``tables`` (ranked comparisons, array and per-antenna summaries, files),
``plots`` (PNG figures), ``wraps`` (reference-band wrap times), ``api``
(:func:`diagnose`) and ``app`` (the CLI entry).
"""

from .api import diagnose

__all__ = ["diagnose"]
