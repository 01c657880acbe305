"""The ``hitops`` command: one subcommand per tool schema, behind one error boundary.

Each subcommand's options come from ``hitops/schemas/<tool>.yml``; its
implementation is the function ``run`` of module ``hitops.<tool>.app``,
imported only when that subcommand runs so ``hitops --help`` stays fast.

The error boundary (:func:`run_tool`) is the same for every tool and for the
Stimela cabs, which run this command:

* bad input (any :class:`hitops.errors.HitopsError`): one line naming the
  file, column, station or value and the remedy; exit status 2 (1 for faults
  the tool itself recognised, such as a failed rollback);
* anything unexpected (casacore, dask, numba, CASA, the OS: a damaged table,
  permission denied, a full disk): one line saying what failed, exit status 1;
  the traceback goes to a file named in that line, and to the screen with
  ``--debug`` (or ``HITOPS_DEBUG=1``);
* SIGINT and SIGTERM: the tool's own clean-up runs (calibrate drops the
  columns it created and restores FLAG), then one line and exit status 130
  or 143; the line says what the run left (a note the tool added to the
  interrupt, e.g. calibrate's committed columns), or that nothing changed.

A missing required option is reported by click before any tool code runs.
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
import sys
import tempfile
import time
import traceback
import warnings

import click

from . import __version__
from .errors import HitopsError
from .logs import setup_logging
from .schema import clickify, tools

log = logging.getLogger("hitops")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, so clean-up code (``finally``, rollbacks) runs.

    A KeyboardInterrupt subclass: code that already cleans up after Ctrl-C
    cleans up after a batch system's SIGTERM in the same way.
    """


def _raise_terminated(signum, frame):
    raise Terminated()


def _one_line(text: str) -> str:
    """A message folded onto one line (casacore and CASA messages span several)."""
    return " ".join(str(text).split())


def _save_traceback(tool: str) -> str:
    """Write the current exception's traceback to a file; its path (or '' if that failed)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = os.path.join(tempfile.gettempdir(), f"hitops-{tool}-{stamp}-{os.getpid()}.traceback.txt")
    try:
        with open(path, "w") as out:
            out.write(f"hitops {__version__} {tool}: {' '.join(sys.argv)}\n\n")
            traceback.print_exc(file=out)
    except OSError:
        return ""
    return path


def _what_is_left(stop: BaseException,
                  unchanged: str = "the input files are as they were before this run; rerun "
                                   "the same command to start again") -> str:
    """What a stopped run leaves: the tool's own note when it had already changed a file
    (``add_note`` where it stopped, e.g. calibrate after its commit), else ``unchanged``."""
    notes = getattr(stop, "__notes__", None)
    if notes:
        return " ".join(_one_line(n) for n in notes)
    return unchanged


def run_tool(tool: str, func, params: dict, debug: bool = False) -> int:
    """Run one tool's function behind the error boundary; the process exit status."""
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        func(**params)
        return 0
    except HitopsError as err:
        # the error, then what the run had done by then (a note added where it stopped),
        # as clauses of one line
        notes = [_one_line(n) for n in getattr(err, "__notes__", [])]
        log.error("%s", "; ".join([_one_line(err).rstrip(".")] + notes) if notes
                  else _one_line(err))
        if debug:
            traceback.print_exc()
        return err.exit_code
    except Terminated as stop:
        log.error("hitops %s: terminated (SIGTERM); %s", tool, _what_is_left(stop))
        return 143
    except KeyboardInterrupt as stop:
        log.error("hitops %s: interrupted; %s", tool, _what_is_left(stop))
        return 130
    except Exception as err:
        saved = _save_traceback(tool)
        kind = type(err).__name__
        detail = _one_line(err) or "no message"
        if debug:
            traceback.print_exc()
        left = _what_is_left(err, "The input files are as they were before this run.")
        log.error("hitops %s failed unexpectedly: %s: %s. %s %s", tool, kind, detail, left,
                  (f"Details in {saved}; rerun with --debug to print them."
                   if saved else "Rerun with --debug for the details."))
        return 1
    finally:
        signal.signal(signal.SIGTERM, previous)


def _make_command(tool: str) -> click.Command:
    def invoke(debug=False, **params):
        setup_logging()
        # on a cluster (--scheduler) the inputs of each task travel in the graph by
        # design: distributed's advice to load them with dask instead is not the user's
        warnings.filterwarnings("ignore", "Sending large graph", UserWarning)
        module = importlib.import_module(f"hitops.{tool}.app")
        debug = debug or os.environ.get("HITOPS_DEBUG", "") not in ("", "0")
        sys.exit(run_tool(tool, module.run, params, debug))

    command = clickify(tool, invoke)
    command.params.append(click.Option(
        ["--debug"], is_flag=True, default=False,
        help="print the full traceback of an unexpected error (also: HITOPS_DEBUG=1)"))
    return command


@click.group()
@click.version_option(__version__, prog_name="hitops")
def cli():
    """HITOPS: frequency phase transfer for mm-VLBI at arbitrary frequency ratios."""


for _tool in tools():
    cli.add_command(_make_command(_tool))


def main():
    cli()


if __name__ == "__main__":
    main()
