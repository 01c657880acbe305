"""Entry point of ``hitops calibrate``: the Python function itself (parameters and defaults
from hitops/schemas/calibrate.yml; tests/test_schema_defaults.py keeps them equal)."""

from .api import calibrate as run  # noqa: F401
