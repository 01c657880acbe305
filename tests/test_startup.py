"""The command line's lean start-up and fast exit (hitops/startup.py), each in its own process."""

import subprocess
import sys
import textwrap

import numpy as np
from casacore import tables as pt



def run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=300)


def test_lean_start_skips_scipy_then_lets_it_be_imported():
    proc = run_python("""
        import sys
        from hitops.startup import lean_start
        hidden = lean_start()
        print("hidden", sorted(hidden))
        print("scipy loaded by the stack", "scipy" in sys.modules)
        import dask.array, numpy as np
        from hitops.kernels.wraps import count_wraps
        phase = np.array([3.0, -3.0, -2.9, 3.1])
        print("wraps", count_wraps(phase, np.ones(4, bool)).tolist())
        print("dask", float(dask.array.ones(4, chunks=2).sum().compute()))
        import scipy.linalg
        print("scipy importable", scipy.linalg.__name__)
        import gc
        print("imports frozen", gc.get_freeze_count() > 10000)
    """)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "hidden ['jinja2', 'scipy']" in out
    assert "scipy loaded by the stack False" in out
    assert "wraps [0, -1, -1, 0]" in out   # a step down across +-pi, then back up
    assert "dask 4.0" in out
    assert "scipy importable scipy.linalg" in out
    assert "imports frozen True" in out


def test_lean_start_leaves_an_imported_scipy_alone():
    proc = run_python("""
        import scipy
        from hitops.startup import lean_start
        print("hidden", lean_start(numba_target=False))
    """)
    assert proc.returncode == 0, proc.stderr
    assert "hidden ['jinja2']" in proc.stdout


def test_fast_exit_flushes_open_tables_and_streams(tmp_path):
    path = tmp_path / "t.tab"
    desc = pt.maketabdesc([pt.makescacoldesc("X", 0.0)])
    with pt.table(str(path), desc, nrow=3, ack=False) as t:
        t.putcol("X", np.zeros(3))
    proc = run_python(f"""
        import sys
        from casacore import tables as pt
        from hitops.startup import fast_exit
        from hitops.startup import lean_start
        lean_start(numba_target=False)   # tables opened after the freeze are still found
        t = pt.table({str(path)!r}, readonly=False, ack=False)
        t.putcol("X", [1.5, 2.5, 3.5])        # left open: only fast_exit can flush it
        keep = [t]
        sys.stdout.write("no newline, still buffered")
        fast_exit(3)
    """)
    assert proc.returncode == 3, proc.stderr
    assert proc.stdout == "no newline, still buffered"
    with pt.table(str(path), ack=False) as t:
        assert t.getcol("X").tolist() == [1.5, 2.5, 3.5]
