"""Whole-column reads and writes of a Measurement Set, for the tests' checks and corruptions."""

from casacore import tables as pt


def col(ms, name):
    with pt.table(str(ms), ack=False) as t:
        return t.getcol(name)


def put(ms, name, values):
    with pt.table(str(ms), readonly=False, ack=False) as t:
        t.putcol(name, values)
