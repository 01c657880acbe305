"""Frequency phase transfer (CFPT, CWU, PWC) between two Measurement Sets.

``calibrate(ref_ms, target_ms, method="pwc", ...)`` is the Python API of
``hitops calibrate``; see docs/calibrate.md.
"""


def calibrate(ref_ms, target_ms, **kwargs):
    """See :func:`hitops.calibrate.api.calibrate` (imported lazily to keep the CLI fast)."""
    from .api import calibrate as _calibrate

    return _calibrate(ref_ms, target_ms, **kwargs)
