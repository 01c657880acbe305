"""Floors to compare ``hitops calibrate`` timings with, each measured as a whole process.

* ``issue``: the I/O floor as issue 2 defines it, a python-casacore script that
  reads the two input DATA columns and writes one output column;
* ``same_columns``: a python-casacore script that reads every main-table column
  ``hitops calibrate --method pwc`` reads (TIME, ANTENNA1, ANTENNA2,
  SCAN_NUMBER, INTERVAL, FLAG_ROW, DATA and FLAG of both bands) and writes
  the one column it writes: the fair floor for the same work;
* ``same_stack``: the same-columns floor run after importing the stack that
  ``hitops calibrate`` imports (below) and starting numba's CPU target: start-up
  plus the same I/O, the floor a whole ``hitops calibrate`` process is held to
  (issue 28);
* ``imports_plain``: a process that only imports what ``hitops calibrate`` needs
  (the CLI, numpy, numba and the kernels module, python-casacore, dask and
  dask-ms), starts numba's CPU target and exits normally, touching no data: the
  fixed cost of the required stack, as the ``hitops`` command pays it (it
  imports the stack plainly and exits through the interpreter's teardown).

Each script is written to the work directory and run by
:func:`benchmarks._report.run_process`.  The output column is created the
first time and overwritten afterwards, as ``--overwrite`` does.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ._report import median, run_process

_READ_WRITE = """
import sys
from casacore import tables as pt
ref, target, columns = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
with pt.table(ref, ack=False) as t:
    ref_cols = {c: t.getcol(c) for c in columns}
with pt.table(target, readonly=False, ack=False) as t:
    tgt_cols = {c: t.getcol(c) for c in columns}
    if "FLOOR_DATA" not in t.colnames():
        desc = t.getcoldesc("DATA")
        desc["name"] = "FLOOR_DATA"
        t.addcols(pt.makecoldesc("FLOOR_DATA", desc))
    t.putcol("FLOOR_DATA", tgt_cols["DATA"])
"""

_IMPORTS_PLAIN = """
import numpy, numba, dask, dask.array, daskms, casacore.tables
import hitops.cli, hitops.calibrate.api, hitops.kernels.fpt
from numba.core.registry import cpu_target
cpu_target.target_context.refresh()   # what the first kernel call does
"""

_SAME_STACK = _IMPORTS_PLAIN + _READ_WRITE

CALIBRATE_COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "INTERVAL", "FLAG_ROW",
                     "DATA", "FLAG"]

LABELS = {
    "issue": "I/O floor (issue 2: python-casacore reads 2 x DATA, writes 1 column)",
    "same_columns": "I/O floor, same columns as calibrate (8 columns x 2 bands read, 1 written)",
    "same_stack": "Same-stack floor: import the stack, start numba's CPU target, then the "
                  "same-columns read and write",
    "imports_plain": "start-up only, plain: import the stack (numpy, numba, dask, dask-ms, casacore), "
                     "start numba's CPU target, normal exit",
}


def floor_commands(workdir: Path, ref_ms, target_ms):
    """{name: command} for the floors (scripts written into ``workdir``)."""
    workdir = Path(workdir)
    rw = workdir / "io_floor.py"
    rw.write_text(_READ_WRITE)
    plain = workdir / "imports_plain_floor.py"
    plain.write_text(_IMPORTS_PLAIN)
    stack = workdir / "same_stack_floor.py"
    stack.write_text(_SAME_STACK)
    return {
        "issue": [sys.executable, str(rw), str(ref_ms), str(target_ms), "DATA"],
        "same_columns": [sys.executable, str(rw), str(ref_ms), str(target_ms),
                         ",".join(CALIBRATE_COLUMNS)],
        "imports_plain": [sys.executable, str(plain)],
        "same_stack": [sys.executable, str(stack), str(ref_ms), str(target_ms),
                       ",".join(CALIBRATE_COLUMNS)],
    }


def measure_floors(workdir: Path, ref_ms, target_ms, repeats: int = 3, names=None, env=None):
    """{name: {wall_s, cpu_s, peak_rss_mb}} medians (wall, CPU) and max RSS over ``repeats``."""
    out = {}
    for name, cmd in floor_commands(workdir, ref_ms, target_ms).items():
        if names and name not in names:
            continue
        runs = [run_process(cmd, env=env) for _ in range(repeats)]
        out[name] = {"wall_s": median([r["wall_s"] for r in runs]),
                     "cpu_s": median([r["cpu_s"] for r in runs]),
                     "peak_rss_mb": max(r["peak_rss_mb"] for r in runs)}
    return out
