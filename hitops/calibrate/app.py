"""Entry point of ``hitops calibrate``: the Python function with one keyword per flag
(its signature is the schema's, hitops/schemas/calibrate.yml; tests/test_schema_defaults.py
checks it), which makes the option sections and calls :func:`hitops.calibrate.calibrate`."""

from .api import calibrate_flat as run  # noqa: F401
