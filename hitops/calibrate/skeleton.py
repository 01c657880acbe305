"""The one run skeleton of ``hitops calibrate``, whichever reference it transfers.

    prepare (api.py, files.prepare_inputs) -> plan (the source's) -> open the transaction
    -> stage (the source's chunk loop through ChunkIO, into the transaction)
    -> commit (once, interrupts held) -> report (one RunReport, written once)

A :class:`ReferenceSource` is where each chunk's correction comes from: REF_MS's
visibilities with a wrap tracker (:class:`~hitops.calibrate.visibility_source.VisibilitySource`)
or a CASA table solved on REF_MS (:class:`~hitops.calibrate.from_table.TableSource`).  It
plans its run, makes the :class:`~hitops.calibrate.output.OutputTransaction` its writes go
to, stages every chunk's outputs into it and turns what staging returned into the report;
:func:`run_source` does the rest the same way for both: the commit, the rollback on a
failure before it, and what the set holds when a run stops after it.
"""

from __future__ import annotations

from typing import Dict, Protocol, TypeVar

from .commit import committed_note, stage_and_commit
from .output import OutputTransaction

Staged = TypeVar("Staged")


class ReferenceSource(Protocol[Staged]):
    """A planned run's reference: what :func:`run_source` drives."""

    def open_transaction(self) -> OutputTransaction:
        """The run's transaction, checked (free space) and its staging columns made;
        every check that can refuse the run has run before this returns."""

    def stage(self, tx: OutputTransaction) -> Staged:
        """Every chunk corrected and staged into ``tx`` (not committed)."""

    def after_commit(self) -> str:
        """What follows the commit, in words (for a run stopped after it)."""

    def report(self, tx: OutputTransaction, staged: Staged) -> Dict:
        """The run's report from what :meth:`stage` returned, written once; returned."""


def run_source(source: ReferenceSource) -> Dict:
    """Open, stage, commit, report: the run of a planned ``source``."""
    tx = source.open_transaction()
    staged = stage_and_commit(tx, lambda: source.stage(tx),
                              lambda: committed_note(tx, source.after_commit()))
    try:
        return source.report(tx, staged)
    except BaseException as stop:
        # an interrupt or a failure after the commit: the set is no longer as it was, and
        # hitops/cli.py says what it holds
        stop.add_note(committed_note(tx, source.after_commit()))
        raise
