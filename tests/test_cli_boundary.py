"""Every command behind one error boundary (issue 11), tried as a user would, in real processes.

For each subcommand: missing, malformed and out-of-range values, and damaged inputs
(a missing storage file, a truncated column file, a missing subtable, a read-only
set).  Each must end with a non-zero exit, no "Traceback", the culprit named, and
every input file as it was.  Then the faults of a run itself: a kill during the
write (nothing that looks like a result is left, and the next run cleans up), and a
file system too small for the new columns.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.testing import PairSpec

HITOPS = Path(sys.executable).with_name("hitops")
pytestmark = pytest.mark.slow


def snapshot(*paths):
    """sha1 of every file below ``paths`` (casacore's lock file aside)."""
    out = {}
    for root in paths:
        root = Path(root)
        files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
        for path in files:
            if path.name != "table.lock":
                out[str(path)] = hashlib.sha1(path.read_bytes()).hexdigest()
    return out


def hitops(*args, cwd=None, timeout=300):
    proc = subprocess.run([str(HITOPS), *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)
    return proc.returncode, proc.stdout + proc.stderr


def refused(args, culprit, inputs=(), code=None, cwd=None):
    """Run hitops with ``args``: non-zero exit, no traceback, ``culprit`` named, inputs intact."""
    before = snapshot(*inputs)
    rc, out = hitops(*args, cwd=cwd)
    assert rc != 0, out
    if code is not None:
        assert rc == code, out
    assert "Traceback" not in out, out
    assert culprit in out, out
    assert snapshot(*inputs) == before
    return out


@pytest.fixture(scope="module")
def pair(pair_store):
    """The session's build, shared: every refusal below checks it is left unchanged."""
    return pair_store.built(PairSpec(n_time=60, seed=5))


@pytest.fixture
def copy(pair, tmp_path):
    """A private copy of the pair for a test that damages it."""
    shutil.copytree(pair.ref_ms, tmp_path / "ref.ms")
    shutil.copytree(pair.target_ms, tmp_path / "target.ms")
    return tmp_path / "ref.ms", tmp_path / "target.ms"


# -- values ------------------------------------------------------------------------------

@pytest.mark.parametrize("args, culprit", [
    (["simulate", "paper"], "Missing option '--outdir'"),
    (["simulate", "nosuchscene", "--outdir", "{tmp}/o"], "nosuchscene"),
    (["simulate", "demo", "--outdir", "{tmp}/o", "--duration", "abc"], "'abc' is not a valid float"),
    (["simulate", "demo", "--outdir", "{tmp}/o", "--duration", "-5"], "duration"),
    (["calibrate", "{ref}"], "Missing argument 'TARGET_MS'"),
    (["calibrate", "{ref}", "{tmp}/nope.ms"], "nope.ms"),
    (["calibrate", "{ref}", "{tgt}", "--chunk-rows", "x"], "'x' is not a valid integer"),
    (["calibrate", "{ref}", "{tgt}", "--chunk-rows", "-1"], "--chunk-rows -1"),
    (["calibrate", "{ref}", "{tgt}", "--memory-budget", "lots"], "--memory-budget lots: give a size"),
    (["calibrate", "{ref}", "{tgt}", "--method", "pwc,foo"], "unknown method 'foo'"),
    (["calibrate", "{ref}", "{tgt}", "--ratio", "-2"], "--ratio -2"),
    (["calibrate", "{ref}", "{tgt}", "--target-column", "NOPE"], "has no column NOPE"),
    (["calibrate", "{ref}", "{tgt}", "--tracker", "magic"], "'magic' is not one of"),
    (["calibrate", "{ref}", "{tgt}", "--lock-timeout", "-1"], "--lock-timeout -1"),
    (["diagnose", "{tmp}/nope.ms"], "nope.ms"),
    (["diagnose", "{tgt}", "--columns", "DATA,NOPE", "--outdir", "{tmp}/d"], "NOPE"),
    (["diagnose", "{tgt}", "--interval", "-3", "--outdir", "{tmp}/d"], "-3"),
    (["compare", "{tmp}/nofit.json", "--outdir", "{tmp}/c"], "nofit.json"),
    (["compare", "x.json"], "Missing option '--outdir'"),
])
def test_bad_values_are_refused_in_one_line(pair, tmp_path, args, culprit):
    fill = {"ref": pair.ref_ms, "tgt": pair.target_ms, "tmp": tmp_path}
    args = [a.format(**fill) for a in args]
    culprit = culprit.format(**fill)
    refused(args, culprit, inputs=[pair.ref_ms, pair.target_ms])


# -- damaged inputs ----------------------------------------------------------------------

def test_missing_storage_file(copy):
    ref, tgt = copy
    (tgt / "table.f0").unlink()
    refused(["calibrate", ref, tgt], "table.f0", inputs=[ref, tgt])
    refused(["diagnose", tgt, "--columns", "DATA", "--outdir", tgt.parent / "d"], "table.f0", inputs=[tgt])


def test_truncated_column_file(copy):
    ref, tgt = copy
    with pt.table(str(tgt), ack=False) as t:
        dm = {c: t.getdminfo(c) for c in ("DATA",)}
    # the DATA column's bucket file, cut to 1 kB
    name = dm["DATA"]["NAME"]
    candidates = sorted(p for p in tgt.glob("table.f*") if p.stat().st_size > 4096)
    data_file = [p for p in candidates if "TSM" in p.name] or candidates
    victim = max(data_file, key=lambda p: p.stat().st_size)
    with open(victim, "r+b") as fh:
        fh.truncate(1024)
    out = refused(["calibrate", ref, tgt], "is damaged", inputs=[ref, tgt])
    assert str(tgt) in out and "column" in out
    assert name  # the data manager exists (the test damages a real column file)
    refused(["diagnose", tgt, "--columns", "DATA", "--outdir", tgt.parent / "d"], "is damaged", inputs=[tgt])


def test_missing_subtable(copy):
    ref, tgt = copy
    shutil.rmtree(tgt / "ANTENNA")
    refused(["calibrate", ref, tgt], "has no ANTENNA subtable", inputs=[ref, tgt])
    refused(["diagnose", tgt, "--columns", "DATA", "--outdir", tgt.parent / "d"], "has no ANTENNA subtable",
            inputs=[tgt])


def _mount(*args) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.fixture
def read_only(copy, tmp_path):
    """The copied pair behind a read-only bind mount (skipped where mounting is not allowed)."""
    view = tmp_path / "ro"
    view.mkdir()
    if os.geteuid() != 0 or not _mount("--bind", str(copy[0].parent), str(view)):
        pytest.skip("needs root to bind-mount read-only")
    try:
        if not _mount("-o", "remount,bind,ro", str(view)):
            pytest.skip("read-only remount not permitted here")
        yield view / "ref.ms", view / "target.ms"
    finally:
        subprocess.run(["umount", str(view)], capture_output=True)


def test_read_only_measurement_set(read_only):
    ref, tgt = read_only
    out = refused(["calibrate", ref, tgt], "cannot be written", inputs=[ref, tgt], code=2)
    assert str(tgt) in out and "copy the set" in out


def test_read_only_output_directory(pair, read_only):
    ref, _ = read_only
    out_dir = ref.parent / "sim-out"
    refused(["simulate", "demo", "--outdir", out_dir, "--duration", "60"], str(out_dir))


# -- faults of a run -----------------------------------------------------------------------

KILL_DURING_WRITE = textwrap.dedent("""
    import os, signal, sys
    import hitops.io.read as msio
    original = msio.write_main_columns
    def write_then_die(*args, **kwargs):
        original(*args, **kwargs)          # the first chunk's columns reach the disk ...
        os.kill(os.getpid(), signal.SIGKILL)   # ... and the process dies mid-run
    msio.write_main_columns = write_then_die
    from hitops.calibrate import calibrate_flat
    calibrate_flat(sys.argv[1], sys.argv[2], method="pwc,cfpt", chunk_rows=100)
""")


def test_a_run_killed_while_writing_leaves_no_result(copy):
    ref, tgt = copy
    with pt.table(str(tgt), ack=False) as t:
        before_cols, before_flag = sorted(t.colnames()), t.getcol("FLAG")
    proc = subprocess.run([sys.executable, "-c", KILL_DURING_WRITE, str(ref), str(tgt)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    with pt.table(str(tgt), ack=False) as t:
        after = t.colnames()
        assert np.array_equal(t.getcol("FLAG"), before_flag)
    # nothing complete-looking: only columns marked unfinished were added
    new = sorted(set(after) - set(before_cols))
    assert new and all(c.startswith("HITOPS_PARTIAL_") for c in new), new
    # the next run (no --overwrite needed) removes them, says so, and finishes
    rc, out = hitops("calibrate", ref, tgt, "--method", "pwc,cfpt")
    assert rc == 0, out
    assert "unfinished columns of an earlier run" in out
    with pt.table(str(tgt), ack=False) as t:
        assert not any(c.startswith("HITOPS_PARTIAL_") for c in t.colnames())
        assert {"PWC_DATA", "CFPT_DATA"} <= set(t.colnames())


def test_interrupt_during_write_rolls_back(copy):
    """SIGTERM mid-run: the tool's clean-up runs and the set is as it was."""
    ref, tgt = copy
    script = KILL_DURING_WRITE.replace("signal.SIGKILL", "signal.SIGTERM").replace(
        "from hitops.calibrate import calibrate_flat\n",
        "from hitops.cli import run_tool\nfrom hitops.calibrate import calibrate_flat\n").replace(
        'calibrate_flat(sys.argv[1], sys.argv[2], method="pwc,cfpt", chunk_rows=100)',
        'sys.exit(run_tool("calibrate", calibrate_flat, dict(ref_ms=sys.argv[1], '
        'target_ms=sys.argv[2], method="pwc,cfpt", chunk_rows=100)))')
    before = snapshot(ref, tgt)
    proc = subprocess.run([sys.executable, "-c", script, str(ref), str(tgt)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 143, proc.stderr
    assert "terminated" in proc.stderr and "Traceback" not in proc.stderr
    with pt.table(str(tgt), ack=False) as t:
        assert not any(c.startswith("HITOPS_PARTIAL_") for c in t.colnames())
    after = snapshot(ref, tgt)
    # the table files that hold the column list change with any add/remove; the data do not
    with pt.table(str(tgt), ack=False) as t:
        assert "PWC_DATA" not in t.colnames()
    assert {k for k in before if "table.f" in k} <= set(after)


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def test_full_disk_is_refused_before_writing(tmp_path, shared_pair):
    """On a file system with room for the pair but not for three new columns: refused
    before anything is written (a write that runs out of space can abort casacore)."""
    # only read: copied onto the small file system below
    truth = shared_pair(PairSpec(n_time=1500, n_ant=4, corr_types=("RR", "RL", "LR", "LL"), seed=9))
    pair_bytes = _size(truth.ref_ms) + _size(truth.target_ms)
    new_bytes = truth.time.size * 4 * (8 * 3 + 2)
    mnt = tmp_path / "small"
    mnt.mkdir()
    size_kb = (pair_bytes + new_bytes // 2) // 1024 + 64
    if os.geteuid() != 0 or not _mount("-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(mnt)):
        pytest.skip("needs root to mount a small tmpfs")
    try:
        ref, tgt = mnt / "ref.ms", mnt / "target.ms"
        shutil.copytree(truth.ref_ms, ref)
        shutil.copytree(truth.target_ms, tgt)
        assert new_bytes > shutil.disk_usage(mnt).free
        out = refused(["calibrate", ref, tgt, "--method", "pwc,cfpt,cwu"], "not enough space",
                      inputs=[ref, tgt], code=2)
        assert "MB missing" in out
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


SLOW_WRITE = textwrap.dedent("""
    import sys, time
    import hitops.io.read as msio
    original = msio.write_main_columns
    def slow_write(*args, **kwargs):
        print("writing", flush=True)
        time.sleep(8)                       # a long write: the second run meets the lock
        return original(*args, **kwargs)
    msio.write_main_columns = slow_write
    from hitops.calibrate import calibrate_flat
    calibrate_flat(sys.argv[1], sys.argv[2], method="pwc")
""")


def test_two_runs_on_one_set_the_second_waits_and_says_so(copy):
    ref, tgt = copy
    first = subprocess.Popen([sys.executable, "-c", SLOW_WRITE, str(ref), str(tgt)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert first.stdout.readline().strip() == "writing"
        rc, out = hitops("calibrate", ref, tgt, "--method", "cfpt", "--lock-timeout", "2")
    finally:
        first.wait(timeout=120)
    assert first.returncode == 0, first.stderr.read()
    assert rc == 2 and "Traceback" not in out
    assert "being written by another hitops run" in out and "waited 2 s" in out
    # the first run's result is whole; the second wrote nothing
    with pt.table(str(tgt), ack=False) as t:
        names = t.colnames()
    assert "PWC_DATA" in names and "CFPT_DATA" not in names
    assert not any(c.startswith("HITOPS_PARTIAL_") for c in names)
