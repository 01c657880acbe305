"""One calibrate run's report, whichever reference source it ran on, written once at its end.

A run's report is a :class:`RunReport`: the sections its reference source made (the
visibility path's group report, hitops/calibrate/report.py; the ``--reference-table``
path's, hitops/calibrate/from_table.py, whose tracking section is a :class:`TableTracking`)
and then what followed the commit, each made once: the verdict, ``--caltable``, the
input conversions and ``--export-uvfits`` (:class:`AfterCommit`).  :func:`write_run_report`
turns it into JSON once, when everything is in it (the JSON keys are those users, recipes,
hitops/report and ``hitops diagnose`` read: docs/calibrate.md).

Kept apart from :mod:`hitops.calibrate.report` (which reads the visibility path's plan and
results, and with them dask-ms): the table path imports this module only.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

log = logging.getLogger("hitops.calibrate")


def report_path(opts, target_ms: str) -> Path:
    """Where a run's JSON report goes: --report, else ``<target_ms>.hitops-calibrate.json``."""
    return Path(opts.output.report) if opts.output.report else Path(target_ms + ".hitops-calibrate.json")


@dataclass(frozen=True)
class AntennaWraps:
    """What the table path tracked of one antenna: the wraps counted in its solutions
    (hitops/solutions/wraps.py; the rates bridging the solutions)."""

    antenna: str
    wraps: int                  # wraps counted (sum of |steps| of the count)
    flagged_solutions: int      # solution slots without an unflagged solution
    solutions: int              # unflagged solutions, every window and receptor
    max_residual_rad: float     # largest |bridged residual|: how close to the Itoh limit


@dataclass(frozen=True)
class TableTracking:
    """The tracking section of a ``--reference-table`` run: per antenna (no per-baseline
    tracker); ``baselines`` stays empty, as ``hitops diagnose`` expects of an antenna report."""

    antennas: Tuple[AntennaWraps, ...]
    segments: int               # scans and gaps after which every antenna's count restarts
    wrap_counting: bool         # False: the first method scales the wrapped phases (cfpt)

    def as_json(self) -> Dict:
        return {"setup": {"tracker": "reference-table", "segments": self.segments,
                          "wrap_counting": self.wrap_counting},
                "baselines": [], "antennas": [dataclasses.asdict(a) for a in self.antennas]}


@dataclass
class AfterCommit:
    """What follows the commit, each entry made once (None: not made)."""

    verdict: Optional[Dict] = None
    caltable: Optional[Dict] = None
    conversions: Optional[List] = None
    export_uvfits: Optional[Dict] = None

    def as_json(self) -> Dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclass
class RunReport:
    """A run's report: its reference source's sections (JSON-ready, in report order), then
    what followed the commit."""

    path: Path
    sections: Dict
    after: AfterCommit = field(default_factory=AfterCommit)

    def as_json(self) -> Dict:
        """The JSON object: the sections, then what followed the commit."""
        return {**self.sections, **self.after.as_json()}


def write_run_report(report: RunReport, caltable: Optional[Callable[[], Dict]],
                     finish: Callable[[AfterCommit], None]) -> Dict:
    """What follows the commit, then the JSON written once: ``caltable()`` (--caltable,
    when given) and ``finish`` (the conversions and --export-uvfits,
    hitops/calibrate/files.py) fill ``report.after``.  Returns the JSON object, with
    ``report_path`` (not written into the file)."""
    if caltable is not None:
        report.after.caltable = caltable()
    finish(report.after)
    body = report.as_json()
    report.path.write_text(json.dumps(body, indent=1))
    body["report_path"] = str(report.path)
    return body
