"""hitops/calibrate/skeleton.py: open -> stage -> commit -> report, the same for every source.

A small reference source writes a real target set through a real OutputTransaction
(its output is the target column rotated by a known phase): the skeleton commits what
it staged, rolls back when staging fails (the set as it was), and a failure after the
commit carries the note that says what the set holds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate.output import OutputTransaction
from hitops.calibrate.skeleton import run_source
from hitops.testing import PairSpec

ROTATION = np.exp(-0.5j).astype(np.complex64)


@dataclass(frozen=True)
class RotatingSource:
    """Every row of the target's DATA times ROTATION, in chunks of ``chunk_rows``."""

    target_ms: str
    chunk_rows: int
    fail_in: str = ""           # "stage" or "report": fail there, after the writes so far

    def open_transaction(self) -> OutputTransaction:
        tx = OutputTransaction(self.target_ms, {"pwc": "PWC_DATA"}, "DATA", None,
                               self.chunk_rows, direct_writes=True)
        tx.check_space()
        tx.create_columns()
        return tx

    def stage(self, tx: OutputTransaction) -> int:
        with pt.table(self.target_ms, ack=False) as t:
            n_rows = t.nrows()
        for start in range(0, n_rows, self.chunk_rows):
            with pt.table(self.target_ms, ack=False) as t:
                n = min(self.chunk_rows, n_rows - start)
                data, flag = t.getcol("DATA", start, n), t.getcol("FLAG", start, n)
            tx.write_outputs(np.arange(start, start + n), {"pwc": data * ROTATION}, flag,
                             flag_read=flag)
            if self.fail_in == "stage":
                raise RuntimeError("stage failed after one chunk")
        return n_rows

    def after_commit(self) -> str:
        return "the report"

    def report(self, tx: OutputTransaction, staged: int) -> Dict:
        if self.fail_in == "report":
            raise RuntimeError("report failed")
        return {"rows": staged, "outputs": tx.outputs}


@pytest.fixture
def target(new_pair):
    return str(new_pair(PairSpec(n_ant=3, n_time=50, corr_types=("RR",), seed=2)).target_ms)


def _columns(ms):
    with pt.table(ms, ack=False) as t:
        return t.colnames()


def test_a_source_is_staged_committed_and_reported(target):
    with pt.table(target, ack=False) as t:
        data = t.getcol("DATA")
    report = run_source(RotatingSource(target, chunk_rows=40))
    assert report == {"rows": data.shape[0], "outputs": {"pwc": "PWC_DATA"}}
    with pt.table(target, ack=False) as t:
        np.testing.assert_array_equal(t.getcol("PWC_DATA"), data * ROTATION)
    assert not [c for c in _columns(target) if c.startswith("HITOPS_PARTIAL_")]


def test_a_failing_stage_rolls_back_and_a_failing_report_says_what_the_set_holds(target):
    before = _columns(target)
    with pytest.raises(RuntimeError, match="stage failed"):
        run_source(RotatingSource(target, chunk_rows=40, fail_in="stage"))
    assert _columns(target) == before              # nothing of the run is left
    with pytest.raises(RuntimeError, match="report failed") as err:
        run_source(RotatingSource(target, chunk_rows=40, fail_in="report"))
    assert any("the run had finished writing" in note and "PWC_DATA" in note
               and "(the report) did not finish" in note for note in err.value.__notes__)
    assert "PWC_DATA" in _columns(target)          # committed before the report failed
