"""Entry point of ``hitops compare``: the Python function itself (parameters and defaults
from hitops/schemas/compare.yml; tests/test_schema_defaults.py keeps them equal)."""

from .table import compare as run  # noqa: F401
