"""hitops/signals.py: a real SIGINT/SIGTERM sent during interrupts_held() arrives after it."""

from __future__ import annotations

import os
import signal

import pytest

from hitops.signals import interrupts_held


@pytest.fixture
def default_sigint():
    """Python's own SIGINT handler for the test, whatever the suite inherited: a suite
    started in the background by a non-interactive shell (`make test &`) inherits SIGINT
    ignored, and an ignored signal must stay ignored (hitops.signals keeps it so)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_sigint_waits_for_the_block_then_arrives(default_sigint):
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            os.kill(os.getpid(), signal.SIGINT)
            done.append("first half")      # the block is not cut here ...
            done.append("second half")
    assert done == ["first half", "second half"]   # ... and the interrupt came after it
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_goes_to_the_handler_there_was():
    class Stopped(Exception):
        pass

    def stop(signum, frame):
        raise Stopped(signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        done = []
        with pytest.raises(Stopped):
            with interrupts_held():
                os.kill(os.getpid(), signal.SIGTERM)
                done.append("whole")
        assert done == ["whole"]
        assert signal.getsignal(signal.SIGTERM) is stop
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_nothing_held_nothing_raised():
    with interrupts_held():
        pass


def test_an_ignored_sigint_stays_ignored():
    """A process started with SIGINT ignored (nohup, a background job of a script) is not
    interrupted by one that arrives during the block, and keeps ignoring it after."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        done = []
        with interrupts_held():
            os.kill(os.getpid(), signal.SIGINT)
            done.append("whole")
        assert done == ["whole"]
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
