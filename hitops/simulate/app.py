"""Entry point of ``hitops simulate``: the Python function itself (parameters and defaults
from hitops/schemas/simulate.yml; tests/test_schema_defaults.py keeps them equal)."""

from .api import simulate as run  # noqa: F401
