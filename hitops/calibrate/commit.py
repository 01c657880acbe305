"""The end of every calibrate path that writes: stage the outputs, then commit them once.

The visibility path (hitops/calibrate/api.py) and the ``--reference-table`` path
(from_table.py) both write through an :class:`~hitops.calibrate.output.OutputTransaction`
and end the same way, through :func:`stage_and_commit`.
"""

from __future__ import annotations

from .output import OutputTransaction


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
