"""Pure numba kernels: they never mutate their inputs; thin drivers live beside them.

``wraps``  -- reference-phase wrap counting (the PWC tracker of the paper).
``fpt``    -- frequency phase transfer (PWC, CFPT, CWU) over a (baseline, time) layout.
"""
