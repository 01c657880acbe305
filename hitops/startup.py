"""Faster start-up and shut-down of the ``hitops`` command.

Start-up: the required stack without its optional extras.

A one-second ``hitops calibrate`` spends most of its time starting up, and
about 0.4 s of that (measured; docs/performance.md) goes on SciPy, which
HITOPS never uses but which two of its dependencies import because it is
installed (casatasks needs it):

* ``dask.array`` imports ``scipy.sparse`` (to register sparse chunk types)
  and ``scipy.fftpack`` (to wrap its FFTs), each inside ``try/except ImportError``;
* numba's CPU target, on the first call of any kernel (cached or not), imports
  ``scipy.linalg`` to find BLAS for ``np.linalg`` in compiled code
  (``numba.np.arraymath._check_blas``), also optional.

``dask.widgets`` likewise imports jinja2 for notebook displays.

:func:`lean_start` imports those parts with SciPy and jinja2 hidden, so the
optional hooks are skipped, then un-hides them: a later ``import scipy``
works as usual.  What is given up, in this process only: dask arrays of
``scipy.sparse`` chunks, ``dask.array.fft`` on SciPy's FFTs, notebook HTML
reprs, and ``np.linalg`` inside numba code compiled in this process; no
HITOPS kernel uses any of them (tests/test_startup.py checks the kernels run).
It is applied by the command line only (``hitops.cli``), never on import of
the library, so a Python user of ``hitops`` gets the stack unchanged.

Shut-down: once a tool has finished, the interpreter's own teardown (clearing
every module, running the destructors of numba's and llvmlite's objects) takes
0.3-0.4 s with numba loaded (measured: ``import numba`` plus its CPU target,
then exit, against the same with :func:`fast_exit`).  :func:`fast_exit` does
what matters of it (closes every python-casacore table still open, so its
data are flushed; runs the ``atexit`` handlers; flushes the logs and the
standard streams) and then ends the process without the rest.
"""

from __future__ import annotations

import atexit
import gc
import importlib
import logging
import os
import sys
from contextlib import contextmanager
from typing import Iterator, Sequence

#: optional packages hidden while the stack is imported
OPTIONAL = ("scipy", "jinja2")
#: imported (and, for numba, initialised) while they are hidden
STACK = ("dask", "dask.array", "daskms")


@contextmanager
def hidden(names: Sequence[str]) -> Iterator[list]:
    """Make ``import NAME`` raise ImportError inside the block (for names not yet imported).

    Yields the names actually hidden; an already imported package stays
    as it is (hiding it then would change nothing and could break its users).
    """
    hid = [n for n in names if n not in sys.modules]
    for name in hid:
        sys.modules[name] = None   # the import system's "known to be missing" marker
    try:
        yield hid
    finally:
        for name in hid:
            if sys.modules.get(name, 0) is None:
                del sys.modules[name]


def lean_start(numba_target: bool = True) -> list:
    """Import the stack (and initialise numba's CPU target) with the optional extras hidden.

    Returns the names that were hidden (empty when they were already imported).
    """
    with hidden(OPTIONAL) as hid:
        for module in STACK:
            try:
                importlib.import_module(module)
            except ImportError:
                pass   # the tool itself reports a missing dependency when it needs it
        if numba_target:
            # numba loads its lowering registries (and probes SciPy for BLAS) on the
            # first kernel call; doing it here keeps the probe inside the hidden block
            from numba.core.registry import cpu_target
            cpu_target.target_context.refresh()
    # the ~120 000 objects the imports made live as long as the process: moved out of the
    # collector's way, a full collection (and the table scan of fast_exit) takes ~2 ms
    # instead of ~100 ms (measured after a paper-size calibrate)
    gc.freeze()
    return hid


def close_open_tables() -> int:
    """Close every python-casacore table object still alive; returns how many were found.

    dask-ms closes its tables when their proxies are collected, and HITOPS
    opens the others in ``with`` blocks, so normally none is left; this is
    the guarantee that nothing is lost when the teardown is skipped.
    """
    tables = sys.modules.get("casacore.tables")
    if tables is None:
        return 0
    gc.collect()   # proxies in reference cycles close their tables here
    found = [obj for obj in gc.get_objects() if isinstance(obj, tables.table)]
    for table in found:
        table.close()   # flushes; a second close of a closed table is harmless
    return len(found)


def fast_exit(status: int = 0) -> None:
    """End the process with ``status`` after flushing what matters, skipping the teardown."""
    close_open_tables()
    atexit._run_exitfuncs()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass   # a closed or broken pipe: nothing more can be written to it
    os._exit(status)
