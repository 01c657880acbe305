"""Pure numba kernels: they never mutate their inputs; thin drivers live beside them.

``fpt``         -- frequency phase transfer (PWC, CFPT, CWU) over a (baseline, time) layout.
``segments``    -- the n0 step's per-segment sums and the 2 pi eps k shift of a kept output.
``coherence``   -- segment coherence of (baseline, series) grids (diagnose).
``sorted_runs`` -- distinct times and look-ups in run-sorted columns.

The wrap trackers' kernels sit beside their trackers in :mod:`hitops.tracking`.
"""
