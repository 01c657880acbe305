"""Run one casatasks task and turn SEVERE log lines into exceptions."""

from __future__ import annotations

import logging
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterable, List

from ..casa_env import ensure_casa_offline
from ..errors import ExternalToolError

log = logging.getLogger("hitops.casa")

#: SEVERE messages that do not mean the task failed.  casatools 6.7 with the
#: casadata measures logs one about the TAI_UTC leap-second table on first use
#: of the measures; the task still runs correctly (GUIDE.md section 3).
#: The message spans three SEVERE lines, all from MeasTable::dUTC.
HARMLESS_SEVERE = (
    re.compile(r"MeasTable::dUTC"),
    re.compile(r"TAI_UTC"),
)

_SEVERE = re.compile(r"\bSEVERE\b")


def severe_lines(lines: Iterable[str]) -> List[str]:
    """The SEVERE lines of a CASA log excerpt, without the harmless ones."""
    found = []
    for line in lines:
        if _SEVERE.search(line) and not any(p.search(line) for p in HARMLESS_SEVERE):
            found.append(line.rstrip())
    return found


def _casalog():
    ensure_casa_offline()
    from casatasks import casalog  # imported late: needs the offline configuration

    return casalog


def _log_path(casalog) -> Path:
    """The CASA log file of this process, moved out of the working directory.

    CASA writes casa-<date>.log into the current directory by default; a
    pipeline step should not litter its working directory, so the log goes to
    $HITOPS_CASA_LOG or a per-process file in the temporary directory.
    """
    wanted = os.environ.get("HITOPS_CASA_LOG") or str(
        Path(tempfile.gettempdir()) / f"hitops-casa-{os.getpid()}.log")
    if casalog.logfile() != wanted:
        casalog.setlogfile(wanted)
    return Path(wanted)


def run_task(name: str, **kwargs: Any) -> Any:
    """Call ``casatasks.<name>(**kwargs)``; raise on an exception or a SEVERE line.

    Returns whatever the task returned.  The log lines the task wrote are
    re-emitted at debug level and, on failure, quoted in the exception.
    """
    casalog = _casalog()
    import casatasks

    task = getattr(casatasks, name, None)
    if task is None:
        raise ExternalToolError(f"casatasks has no task '{name}'")
    logfile = _log_path(casalog)
    start = logfile.stat().st_size if logfile.exists() else 0
    log.info("CASA %s(%s)", name, ", ".join(f"{k}={v!r}" for k, v in kwargs.items()))
    error = None
    result = None
    try:
        result = task(**kwargs)
    except Exception as err:  # CASA raises RuntimeError/AssertionError/ValueError...
        error = err
    text = ""
    if logfile.exists():
        with open(logfile, "r", errors="replace") as fh:
            fh.seek(start)
            text = fh.read()
    lines = text.splitlines()
    for line in lines:
        log.debug("casa: %s", line)
    severe = severe_lines(lines)
    if error is not None or severe:
        detail = "\n  ".join(severe[-10:]) if severe else ""
        cause = f"{type(error).__name__}: {error}" if error is not None else "SEVERE error(s) in the CASA log"
        raise ExternalToolError(
            f"CASA task {name} failed ({cause}); log {logfile}"
            + (f":\n  {detail}" if detail else "")) from error
    return result
