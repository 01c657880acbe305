"""Run one casatasks task and turn SEVERE log lines into exceptions."""

from __future__ import annotations

import ctypes
import logging
import os
import re
import sys
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, List, Optional

from ..casa_env import ensure_casa_offline
from ..errors import ExternalToolError

log = logging.getLogger("hitops.casa")

#: SEVERE messages that do not mean the task failed.  casatools 6.7 logs one
#: about the TAI_UTC leap-second table when the table in casadata is more than
#: a few months older than today's date (casadata 2025.9.22's is dated
#: 2025-09-16); it spans three SEVERE lines, all from MeasTable::dUTC.  No leap
#: second has been announced since 2017, so the table is still right for any
#: date the simulations use.  These lines are kept in the CASA log and replaced
#: by one note in ours (:data:`LEAP_SECOND_NOTE`).
HARMLESS_SEVERE = (
    re.compile(r"MeasTable::dUTC"),
    re.compile(r"TAI_UTC"),
)

LEAP_SECOND_NOTE = ("CASA logged its leap-second message (SEVERE 'Leap second table TAI_UTC "
                    "seems out-of-date': casadata's table is older than six months); harmless "
                    "here, no leap second has been added since 2017")

_SEVERE = re.compile(r"\bSEVERE\b")
# date, priority, origin, message; a continued message has an origin ending in "+"
_WARN = re.compile(r"\tWARN\t([^\t]*)\t(.*)$")
_CASA_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s")
# what CASA's solvers print straight to the console (captured into the log by
# run_task), one line per interval: "Insufficient unflagged antennas to proceed
# with this solve.", "8 of 16 solutions flagged due to SNR < 3 in spw=0 at ...";
# an indented "(time=...)" line continues the one before
_CONSOLE = re.compile(r"^\s*([^\s(].*)$")


def severe_lines(lines: Iterable[str]) -> List[str]:
    """The SEVERE lines of a CASA log excerpt, without the harmless ones."""
    found: List[str] = []
    for line in lines:
        if _SEVERE.search(line) and not any(p.search(line) for p in HARMLESS_SEVERE):
            if line.rstrip() not in found:   # the console copy of a logged line
                found.append(line.rstrip())
    return found


def warning_summary(lines: Iterable[str], top: int = 3) -> List[str]:
    """The most frequent WARN and console messages of a CASA log excerpt, with counts.

    CASA's solvers print a line for every interval they flag or cannot solve
    (3,393 "N of M solutions flagged due to SNR < 3" on the paper scene; with
    too few stations "Insufficient unflagged antennas" in every interval); one
    line with the count says the same.  Numbers are replaced by '#'.
    """
    counts: Counter = Counter()
    for line in lines:
        match = _WARN.search(line)
        console = None if _CASA_LINE.match(line) else _CONSOLE.match(line)
        if (match and not match.group(1).endswith("+")) or console:
            text = (match.group(2) if match else console.group(1)).strip()
            # the interval or antenna named in a message differs from line to line
            text = re.sub(r"\d[\d:/.,]*", "#", text)
            counts[text[:120]] += 1
    return [f"{n} x {text}" for text, n in counts.most_common(top)]


def _casalog():
    ensure_casa_offline()
    from casatasks import casalog  # imported late: needs the offline configuration

    return casalog


def log_path(default_dir: Optional[str] = None) -> Path:
    """Where CASA's log of a task goes: $HITOPS_CASA_LOG, else casa.log in ``default_dir``.

    ``default_dir`` is the directory of the task's output (the calibration
    table, the applycal receipt, the fit file), so a step's CASA log stays
    beside its results; ``python -m hitops.run`` sets HITOPS_CASA_LOG to the
    run's log directory.  Never the working directory nor /tmp.
    """
    explicit = os.environ.get("HITOPS_CASA_LOG")
    if explicit:
        return Path(explicit)
    return Path(default_dir or ".") / "casa.log"


#: task arguments naming the task's output, then its input, in order of preference
_PATH_ARGS = ("caltable", "outputvis", "outfile", "fitsfile", "vis", "imagename", "fitsimage")


def _output_dir(kwargs: dict) -> Optional[str]:
    """The directory of the first file a task's arguments name (its output if named)."""
    for key in _PATH_ARGS:
        value = kwargs.get(key)
        if isinstance(value, (str, Path)) and str(value):
            return str(Path(value).resolve().parent)
    return None


def _select_log(casalog, wanted: Path) -> Path:
    wanted.parent.mkdir(parents=True, exist_ok=True)
    if casalog.logfile() != str(wanted):
        casalog.setlogfile(str(wanted))
    # CASA's lines go to the file only: the SEVERE ones are raised by run_task,
    # the rest would drown a pipeline's output (thousands of WARN lines)
    casalog.showconsole(False)
    return wanted


@contextmanager
def _console_to(path: Path):
    """Send what C++ code prints on stdout/stderr to ``path`` for the duration.

    CASA's solvers print "Insufficient unflagged antennas to proceed with this
    solve." for every interval without a solution straight to the console
    (4,576 lines on the paper scene), and casalog echoes SEVERE lines there:
    they belong in CASA's log with the rest.
    """
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = (os.dup(1), os.dup(2))
    try:
        with open(path, "ab") as fh:
            os.dup2(fh.fileno(), 1)
            os.dup2(fh.fileno(), 2)
        yield
    finally:
        try:
            ctypes.CDLL(None).fflush(None)   # C stdio buffers, before the descriptors move back
        except (OSError, AttributeError):
            pass
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def run_task(name: str, *, log_dir: Optional[str] = None, **kwargs: Any) -> Any:
    """Call ``casatasks.<name>(**kwargs)``; raise on an exception or a SEVERE line.

    Returns whatever the task returned.  CASA's log goes to :func:`log_path`
    (``log_dir``: the directory of the task's output; by default that of the
    first of caltable, outputvis, outfile, fitsfile, vis, imagename); the lines the task
    wrote are re-emitted at debug level, summarised (most frequent warnings)
    at info level and, on failure, quoted in the exception.
    """
    casalog = _casalog()
    import casatasks

    task = getattr(casatasks, name, None)
    if task is None:
        raise ExternalToolError(f"casatasks has no task '{name}'")
    logfile = _select_log(casalog, log_path(log_dir or _output_dir(kwargs)))
    start = logfile.stat().st_size if logfile.exists() else 0
    log.info("CASA %s(%s)", name, ", ".join(f"{k}={v!r}" for k, v in kwargs.items()))
    error = None
    result = None
    try:
        with _console_to(logfile):
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
    if any(_SEVERE.search(line) and any(p.search(line) for p in HARMLESS_SEVERE)
           for line in lines):
        # filtered from the failure check; the note sits right after the lines in CASA's log
        casalog.post(f"hitops: the SEVERE leap-second lines above are not an error: {LEAP_SECOND_NOTE}",
                     "INFO", "hitops")
        log.debug(LEAP_SECOND_NOTE)
    for summary in warning_summary(lines):
        log.info("CASA %s: %s (log %s)", name, summary, logfile)
    severe = severe_lines(lines)
    if error is not None or severe:
        detail = "\n  ".join(severe[-10:]) if severe else ""
        cause = f"{type(error).__name__}: {error}" if error is not None else "SEVERE error(s) in the CASA log"
        raise ExternalToolError(
            f"CASA task {name} failed ({cause}); log {logfile}"
            + (f":\n  {detail}" if detail else "")) from error
    return result
