"""Frequency phase transfer (CFPT, CWU, PWC) between two Measurement Sets.

``calibrate(ref_ms, target_ms, method="pwc", ...)`` is the Python API of
``hitops calibrate``; see docs/calibrate.md.
"""

from .api import calibrate

__all__ = ["calibrate"]
