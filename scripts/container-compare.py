#!/usr/bin/env python3
"""Compare two result JSON files (e.g. peak-flux.json of a native run and of a
run inside the image or through slurm): every number must be identical.

    scripts/container-compare.py REFERENCE.json OTHER.json [LABEL]

Strings that are paths differ between the runs (/check/demo/... inside the
image), so only their last component is compared.  Prints one line per
difference (at most 20) and exits 1, or one "identical" line and exits 0.
Standard library only, so any Python 3 runs it.
"""

import json
import math
import sys
from pathlib import PurePosixPath


def walk(a, b, where, out):
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only in {'reference' if k in a else 'other'}")
            else:
                walk(a[k], b[k], f"{where}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{where}: {len(a)} vs {len(b)} entries")
        for i, (x, y) in enumerate(zip(a, b)):
            walk(x, y, f"{where}[{i}]", out)
    elif isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        if a is not b:
            out.append(f"{where}: {a!r} vs {b!r}")
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)):
        # exact: same code, same wheels, same WSClean must give the same bits
        same = (a == b) or (isinstance(a, float) and isinstance(b, float)
                            and math.isnan(a) and math.isnan(b))
        if not same:
            out.append(f"{where}: {a!r} vs {b!r} (difference {b - a:.3g})")
    elif isinstance(a, str) and isinstance(b, str):
        if "/" in a or "/" in b:
            a, b = PurePosixPath(a).name, PurePosixPath(b).name
        if a != b:
            out.append(f"{where}: {a!r} vs {b!r}")
    elif a != b:
        out.append(f"{where}: {a!r} ({type(a).__name__}) vs {b!r} ({type(b).__name__})")


def main(argv):
    if len(argv) not in (3, 4):
        print("usage: scripts/container-compare.py REFERENCE.json OTHER.json [LABEL]",
              file=sys.stderr)
        return 2
    ref_path, other_path = argv[1], argv[2]
    label = argv[3] if len(argv) == 4 else other_path
    try:
        ref = json.loads(open(ref_path).read())
        other = json.loads(open(other_path).read())
    except (OSError, ValueError) as err:
        print(f"container-compare: cannot read the results ({err}); did both runs finish?",
              file=sys.stderr)
        return 1
    diffs = []
    walk(ref, other, "$", diffs)
    if diffs:
        for line in diffs[:20]:
            print(f"DIFFERENT {line}")
        print(f"container-compare: {label}: {len(diffs)} value(s) differ from {ref_path}",
              file=sys.stderr)
        return 1
    n = sum(1 for _ in _numbers(ref))
    print(f"identical: {label} and {ref_path} ({n} numbers)")
    return 0


def _numbers(x):
    if isinstance(x, dict):
        for v in x.values():
            yield from _numbers(v)
    elif isinstance(x, list):
        for v in x:
            yield from _numbers(v)
    elif isinstance(x, (int, float)) and not isinstance(x, bool):
        yield x


if __name__ == "__main__":
    sys.exit(main(sys.argv))
