"""Frequency phase transfer (CFPT, CWU, PWC) between two Measurement Sets.

``calibrate(ref_ms, target_ms, input=..., tracking=..., n0=..., output=..., run=...)``
is the Python API of ``hitops calibrate``, its options in sections (each a frozen
dataclass from hitops/schemas/calibrate.yml); ``calibrate_flat(ref_ms, target_ms,
method="pwc", ...)`` takes the command line's flags by name.  See docs/calibrate.md.
"""

from .api import (InputOptions, N0Options, OutputOptions, RunOptions, TrackingOptions,
                  calibrate, calibrate_flat)

__all__ = ["calibrate", "calibrate_flat", "InputOptions", "TrackingOptions", "N0Options",
           "OutputOptions", "RunOptions"]
