"""Multi-band (one channel or wideband) mm-VLBI simulator: ``hitops simulate`` and :func:`simulate`."""

from .api import simulate
from .scene import Scene, apply_overrides, parse_scene

__all__ = ["simulate", "parse_scene", "apply_overrides", "Scene"]
