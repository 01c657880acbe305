"""Holding SIGINT and SIGTERM back while a step that must not be cut in two runs.

A commit that renames columns and rewrites FLAG block by block, stopped half
way, would leave a set that is neither the old one nor the new one.  Inside
:func:`interrupts_held` such a signal is only recorded; when the block ends
(whole), the signal's own handler runs, so the interrupt arrives just after it.
"""

from __future__ import annotations

import contextlib
import signal
import threading

HELD = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def interrupts_held():
    """Run the block whole; a SIGINT/SIGTERM that arrives meanwhile is delivered after it.

    Outside the main thread (where Python runs no signal handler) the block runs as
    it is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived = []
    previous = {sig: signal.signal(sig, lambda signum, frame: arrived.append((signum, frame)))
                for sig in HELD}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    for signum, frame in arrived[:1]:
        handler = previous[signum]
        if callable(handler):
            handler(signum, frame)
        elif handler == signal.SIG_DFL and signum == signal.SIGINT:
            raise KeyboardInterrupt
        elif handler == signal.SIG_DFL:
            signal.raise_signal(signum)
