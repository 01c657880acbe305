"""Entry point of ``hitops diagnose``: the Python function itself (parameters and defaults
from hitops/schemas/diagnose.yml; tests/test_schema_defaults.py keeps them equal)."""

from .api import diagnose as run  # noqa: F401
