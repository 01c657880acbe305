"""Every recipe step of a run, read from the log Stimela writes for the recipe.

Stimela 2.1.4 writes ``log-<recipe>.txt`` in the run's log directory: a
"processing step 'NAME'" line with its time as each top-level step starts, and
"all required outputs are OK, skipping this step" when a step's outputs were
fresh.  A step's time is the gap to the next step's start (the last step ran
until the log's last line).  The quiet runner (python -m hitops.run) keeps the
same files in DIR/logs/latest; plain ``stimela run`` in the recipe's opts.log.dir.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import List, Optional, Sequence

from ..recipe_params import RESTORE_STEP

_STAMP = r"(?P<when>\d{4}-\d\d-\d\d \d\d:\d\d:\d\d)"
_START = re.compile(_STAMP + r" STIMELA\.(?P<recipe>[\w-]+) INFO: processing step '(?P<step>[^']+)'")
_SKIP = "all required outputs are OK, skipping this step"
_COND = "skipping step based on conditonal settings"   # sic, Stimela 2.1.4
_WARN = re.compile(_STAMP + r" STIMELA\.[\w.-]+ (?P<level>WARNING|ERROR): (?P<text>.*)")
_CHANGED = re.compile(r"parameters changed for: (?P<steps>[\w, -]+)")
#: bookkeeping steps that run every time and are not work
BOOKKEEPING = {"params", "report"}
_INNER = re.compile(r"INFO: processing step '(?P<step>[^']+)'")


def _sub_recipe_fresh(log_dir: Path, recipe: str, step: str) -> bool:
    """A sub-recipe step whose inner steps (its flag restore aside) all skipped."""
    sub = log_dir / f"log-{recipe}.{step}.txt"
    if not sub.is_file():
        return False
    text = sub.read_text(errors="replace")
    started = [m.group("step") for m in _INNER.finditer(text)]
    work = [name for name in started if name != RESTORE_STEP]
    return bool(work) and text.count(_SKIP) >= len(work)


@dataclass(frozen=True)
class StepRecord:
    """One top-level step: what happened and how long it took."""

    name: str
    status: str          # "ran", "up to date", "skipped (condition)", "running"
    why: str
    seconds: Optional[float]


@dataclass(frozen=True)
class StepLog:
    """The steps of one run, its log directory and the warnings of every step."""

    log_dir: Optional[Path]
    recipe: str
    steps: List[StepRecord]
    warnings: List[str]
    started: str


def find_log_dir(run_dir: Path, recipe: str, given: Optional[str]) -> Optional[Path]:
    """The newest log directory holding ``log-<recipe>.txt`` among the usual places."""
    if given:
        return Path(given)
    pattern = f"log-{recipe}.txt" if recipe else "log-*.txt"
    candidates: List[Path] = []
    for base in (run_dir / "logs", Path.cwd() / "out" / "logs", Path.cwd() / "logs"):
        if base.is_dir():
            candidates += [p.parent for p in base.glob(f"*/{pattern}")]
    if not candidates:
        return None
    return max(candidates, key=lambda d: max(p.stat().st_mtime for p in d.glob(pattern)))


def _seconds(a: str, b: str) -> float:
    fmt = "%Y-%m-%d %H:%M:%S"
    return (datetime.strptime(b, fmt) - datetime.strptime(a, fmt)).total_seconds()


def read_steps(log_dir: Optional[Path], recipe: str, changed_params: Sequence[str]) -> StepLog:
    """The recipe's top-level steps from its log (none: an empty record)."""
    if log_dir is None:
        return StepLog(None, recipe, [], [], "")
    logs = sorted(log_dir.glob(f"log-{recipe}.txt" if recipe else "log-*.txt"),
                  key=lambda p: len(p.name))
    if not logs:
        return StepLog(log_dir, recipe, [], [], "")
    lines = logs[0].read_text(errors="replace").splitlines()
    starts, records, warnings = [], [], []
    changed = set(changed_params)
    last_stamp = ""
    for i, line in enumerate(lines):
        stamp = re.match(_STAMP, line)
        if stamp:
            last_stamp = stamp.group("when")
        match = _START.match(line)
        if match and (not recipe or match.group("recipe") == recipe):
            starts.append((i, match.group("step"), match.group("when")))
        warn = _WARN.match(line)
        if warn:
            warnings.append(f"{warn.group('level')}: {warn.group('text').strip()}")
        note = _CHANGED.search(line)
        if note:
            changed |= {s.strip() for s in note.group("steps").split(",")}
    for k, (i, name, when) in enumerate(starts):
        end = starts[k + 1][0] if k + 1 < len(starts) else len(lines)
        body = "\n".join(lines[i:end])
        next_when = starts[k + 1][2] if k + 1 < len(starts) else None
        if next_when is None and name not in BOOKKEEPING:
            next_when = last_stamp      # the recipe's last step ended with the log
        seconds = _seconds(when, next_when) if next_when else None
        if _SKIP in body or _sub_recipe_fresh(log_dir, recipe, name):
            status, why = "up to date", "its outputs were newer than everything it depends on"
        elif _COND in body:
            status, why = "skipped (condition)", "its skip condition held"
        elif name == "report" and k + 1 == len(starts):
            status, why = "running", "the step writing this page"
        else:
            status = "ran"
            why = ("its parameters changed" if name in changed
                   else "bookkeeping: runs every time" if name in BOOKKEEPING
                   else "an output was missing or older than an input")
        records.append(StepRecord(name, status, why, seconds))
    return StepLog(log_dir, recipe, records, warnings, starts[0][2] if starts else last_stamp)
