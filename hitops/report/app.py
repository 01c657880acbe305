"""Entry point of ``hitops report``: the Python function itself (parameters and defaults
from hitops/schemas/report.yml; tests/test_schema_defaults.py keeps them equal)."""

from .api import report as run  # noqa: F401
