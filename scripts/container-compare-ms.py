#!/usr/bin/env python3
"""Check that columns of two Measurement Sets are bit-identical (e.g. the output
of `hitops calibrate` with the threaded scheduler and with --scheduler slurm).

    scripts/container-compare-ms.py A.ms B.ms COLUMN [COLUMN ...]

Prints one line per column and exits 1 when any differs or is missing.
Needs python-casacore (the project's environment).
"""

import sys

import numpy as np
from casacore import tables as pt


def main(argv):
    if len(argv) < 4:
        print("usage: scripts/container-compare-ms.py A.ms B.ms COLUMN [COLUMN ...]",
              file=sys.stderr)
        return 2
    a, b, columns = argv[1], argv[2], argv[3:]
    bad = 0
    with pt.table(a, ack=False) as ta, pt.table(b, ack=False) as tb:
        for c in columns:
            if c not in ta.colnames() or c not in tb.colnames():
                print(f"MISSING {c}: in {a}: {c in ta.colnames()}, in {b}: {c in tb.colnames()}")
                bad += 1
                continue
            x, y = ta.getcol(c), tb.getcol(c)
            # bitwise, NaN == NaN: identical output is the claim, not closeness
            same = x.shape == y.shape and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc")
            if same:
                print(f"identical {c} {x.shape} {x.dtype}")
            else:
                n = int(np.sum(x != y)) if x.shape == y.shape else -1
                print(f"DIFFERENT {c}: {n} element(s) differ ({x.shape} vs {y.shape})")
                bad += 1
    if bad:
        print(f"container-compare-ms: {bad} column(s) differ between {a} and {b}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
