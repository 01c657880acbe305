"""Robust phase-wrap tracking: theory, station terms and the tracking modes.

The numba kernels live in :mod:`hitops.kernels.tracking` and
:mod:`hitops.kernels.antenna`; this package holds the pure-Python helpers:
:mod:`.theory` (exact slip probabilities, recommended windows and
thresholds), :mod:`.stations` (the threshold in SEFD/opacity terms) and
:mod:`.modes` (naive / smooth / antenna over a (baseline, time) grid).
See docs/tracking.md.
"""
