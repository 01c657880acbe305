"""The end of every calibrate run that writes: stage the outputs, then commit them once.

Both reference sources (REF_MS's visibilities, hitops/calibrate/visibility_source.py; a
CASA table, from_table.py) write through an :class:`~hitops.calibrate.output.OutputTransaction`
and end the same way, in the run skeleton (hitops/calibrate/skeleton.py), through
:func:`stage_and_commit`; a run stopped after its commit says what the set holds in the
words of :func:`committed_note`.
"""

from __future__ import annotations

from .output import FLAG_BACKUP, OutputTransaction


def committed_note(tx: OutputTransaction, after: str) -> str:
    """What the target set holds after the commit, for a run stopped before its end:
    ``after`` names what follows the commit (the report, the verdict, --caltable)."""
    columns = ", ".join(tx.outputs.values())
    flags = (f" and the updated FLAG (the flags before hitops in {FLAG_BACKUP})"
             if tx.flag_written else "")
    return (f"the run had finished writing: {tx.target_ms} holds the new {columns}{flags}; "
            f"what follows the commit ({after}) did not finish; rerun the same command with "
            "--overwrite to redo it (the columns come out the same)")


def stage_and_commit(tx: OutputTransaction, stage, note):
    """Run ``stage()``, which writes this run's outputs into ``tx``, then commit ``tx``
    with interrupts held until it is done; return what ``stage()`` returned.

    A failure or an interrupt while staging, or a commit that failed, rolls back; an
    interrupt held back during the commit and delivered after it gets ``note()``: what
    the set holds now (the caller's words).
    """
    from ..signals import interrupts_held

    try:
        staged = stage()
    except BaseException:
        tx.rollback()
        raise
    committed = False
    try:
        # an interrupt during the commit would leave FLAG half rewritten: it waits
        with interrupts_held():
            tx.commit()
            committed = True
    except BaseException as stop:
        if not committed:   # the commit itself failed
            tx.rollback()
        else:               # an interrupt held back during the commit, delivered after it
            stop.add_note(note())
        raise
    return staged
