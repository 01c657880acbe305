"""What every calibrate run's report shares, whichever reference source it ran on.

Kept apart from :mod:`hitops.calibrate.report` (which reads the visibility path's plan and
results, and with them dask-ms): the ``--reference-table`` path imports this module only.
"""

from __future__ import annotations

from pathlib import Path


def report_path(opts, target_ms: str) -> Path:
    """Where a run's JSON report goes: --report, else ``<target_ms>.hitops-calibrate.json``."""
    return Path(opts.report) if opts.report else Path(target_ms + ".hitops-calibrate.json")
