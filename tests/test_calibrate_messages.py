"""What ``hitops calibrate`` prints is its own words, and true at that moment.

* No library warning reaches the terminal: a baseline flagged whole in the
  target (no sample to take a median of) once let numpy's "All-NaN slice
  encountered" and two lines of numpy's source through; every line on stderr
  must now be one of hitops's log lines.

What an interrupted run says is what is in the set at that moment.

A real ``hitops calibrate`` process gets a real SIGINT at a moment its own log
names: before the commit (the plan's "matched ... target rows" line) nothing
may have changed and the message must say so; after the commit (the summary's
"target samples ... not calibrated" line, written once the columns are in the
set, while the verdict still runs) the new column is in the set and the message
must say that instead of "as they were before this run".

The process is stopped (SIGSTOP) as soon as the line is read, sent SIGINT and
continued, so the interrupt lands in the stage after the line whatever the
machine's load.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.testing import PairSpec, Signal

HITOPS = Path(sys.executable).with_name("hitops")


@pytest.fixture
def pair(new_pair):
    truth = new_pair(PairSpec(n_ant=6, n_time=6000, seed=11,
                              signal=Signal(sigma_ref=0.05, sigma_target=0.1)))
    return truth.ref_ms, truth.target_ms


def interrupt_at(ref, tgt, marker: str):
    """Run calibrate, SIGINT it right after the log line containing ``marker``; (exit
    status, log text)."""
    proc = subprocess.Popen([str(HITOPS), "calibrate", str(ref), str(tgt), "--method", "pwc"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            # SIGINT as a terminal gives it, even when the suite itself runs
                            # with it ignored (started in the background by a script)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if marker in line:
            proc.send_signal(signal.SIGSTOP)
            proc.send_signal(signal.SIGINT)
            proc.send_signal(signal.SIGCONT)
            break
    lines.extend(proc.stderr)          # the rest, until the process closes it
    proc.wait(timeout=300)
    return proc.returncode, "".join(lines)


def columns_and_data(ms):
    with pt.table(str(ms), ack=False) as t:
        return set(t.colnames()), t.getcol("DATA"), t.getcol("FLAG")


def test_interrupt_before_the_commit_leaves_the_set_as_it_was(pair):
    ref, tgt = pair
    names, data, flag = columns_and_data(tgt)
    status, text = interrupt_at(ref, tgt, "target rows to")
    assert status == 130, text
    assert "interrupted; the input files are as they were before this run" in text
    after, data_after, flag_after = columns_and_data(tgt)
    assert after == names                      # no column added, none left half written
    assert np.array_equal(data, data_after) and np.array_equal(flag, flag_after)


def test_interrupt_after_the_commit_names_the_new_column(pair):
    ref, tgt = pair
    names, data, flag = columns_and_data(tgt)
    status, text = interrupt_at(ref, tgt, "not calibrated, each counted once")
    assert status == 130, text
    last = text.strip().splitlines()[-1]
    assert "as they were before this run" not in text
    assert f"{tgt} holds the new PWC_DATA" in last, last
    assert "what follows the commit (the verdict and the report) did not finish" in last
    assert "--overwrite" in last
    after, data_after, flag_after = columns_and_data(tgt)
    assert after == names | {"PWC_DATA"}       # the committed column, nothing staged
    assert np.array_equal(data, data_after) and np.array_equal(flag, flag_after)
    # what it says to do works, and gives the same column
    with pt.table(str(tgt), ack=False) as t:
        first = t.getcol("PWC_DATA")
    done = subprocess.run([str(HITOPS), "calibrate", str(ref), str(tgt), "--method", "pwc",
                           "--overwrite"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    with pt.table(str(tgt), ack=False) as t:
        assert np.array_equal(first, t.getcol("PWC_DATA"))


LOG_LINE = re.compile(r"^\d\d:\d\d:\d\d (INFO|WARNING|ERROR) ")


def test_no_library_warning_reaches_the_terminal(new_pair):
    truth = new_pair(PairSpec(n_ant=4, n_time=600, seed=3,
                              signal=Signal(sigma_ref=0.05, sigma_target=0.1)))
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        whole = (t.getcol("ANTENNA1") == 0) & (t.getcol("ANTENNA2") == 1)
        flag[whole] = True                       # one baseline flagged from start to end
        t.putcol("FLAG", flag)
    for extra in ([], ["--overwrite"]):          # first run, then again on the same pair
        done = subprocess.run([str(HITOPS), "calibrate", str(truth.ref_ms),
                               str(truth.target_ms), "--method", "pwc"] + extra,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        strays = [line for line in done.stderr.splitlines() if not LOG_LINE.match(line)]
        assert strays == [], strays
        assert "verdict" in done.stderr


def test_a_failure_after_the_commit_names_the_new_column(pair, tmp_path):
    """Not only an interrupt: an unexpected error after the commit (here the report's
    path is under a file) says what the set holds, not that it is as it was."""
    ref, tgt = pair
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    done = subprocess.run([str(HITOPS), "calibrate", str(ref), str(tgt), "--method", "pwc",
                           "--report", str(blocker / "report.json")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 1
    last = done.stderr.strip().splitlines()[-1]
    assert "as they were before this run" not in last
    assert f"{tgt} holds the new PWC_DATA" in last, last
    assert "PWC_DATA" in columns_and_data(tgt)[0]
