"""The stages of one ``hitops calibrate`` run, numbered once for the code and the docs.

Module docstrings that say "Stage N of ``hitops calibrate``" and the stage table of
docs/architecture.md use these numbers; tests/test_layout.py checks both against
:data:`STAGES`.  A run goes down the stages in order and never climbs back: nothing is
written before stage 4, and the set holds the result only after stage 5.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Tuple


class Stage(enum.IntEnum):
    OPTIONS = 1
    PREPARE = 2
    PLAN = 3
    CHUNK_LOOP = 4
    COMMIT = 5
    REPORT = 6


@dataclass(frozen=True)
class StageInfo:
    """What a stage does, what it hands on, and the modules that do it."""

    stage: Stage
    what: str
    hands_on: str
    modules: Tuple[str, ...]


#: every stage, in the order a run goes through them
STAGES: Tuple[StageInfo, ...] = (
    StageInfo(Stage.OPTIONS, "typed option sections; the mode and what it refuses",
              "CalibrateOptions, Mode",
              ("hitops/options.py", "hitops/calibrate/api.py", "hitops/calibrate/modes.py")),
    StageInfo(Stage.PREPARE, "output files checked, UVFITS/FITS-IDI converted, access and "
              "locks, the columns each band reads",
              "PreparedInputs, Columns",
              ("hitops/calibrate/files.py", "hitops/io/access.py",
               "hitops/calibrate/inputs.py")),
    StageInfo(Stage.PLAN, "both sets' metadata read once, groups paired, the memory budget, "
              "per group the matched stations, times and chunks, R = r + eps, the tracking "
              "setup", "RunPlan [GroupPlan ...]",
              ("hitops/calibrate/plan.py", "hitops/calibrate/groups.py",
               "hitops/calibrate/memory.py", "hitops/calibrate/band_index.py",
               "hitops/calibrate/chunks.py", "hitops/calibrate/tracking_setup.py")),
    StageInfo(Stage.CHUNK_LOOP, "per chunk read -> track -> transfer -> stage, in passes: the "
              "n0 step's first pass, the writing pass, the calibrator step",
              "staged columns, PassResult",
              ("hitops/calibrate/pipeline.py", "hitops/calibrate/passes.py",
               "hitops/calibrate/worker_chunks.py", "hitops/calibrate/chunk_io.py",
               "hitops/calibrate/chunk_read.py", "hitops/calibrate/transfer.py",
               "hitops/calibrate/n0/step.py", "hitops/calibrate/phaseref/step.py",
               "hitops/calibrate/from_table.py")),
    StageInfo(Stage.COMMIT, "the staged columns become the result, whole or not at all",
              "the committed columns and FLAG",
              ("hitops/calibrate/output.py", "hitops/calibrate/commit.py")),
    StageInfo(Stage.REPORT, "the summary, the verdict, --caltable, --export-uvfits, the JSON "
              "report", "the report",
              ("hitops/calibrate/report.py", "hitops/calibrate/verdict.py")),
)
