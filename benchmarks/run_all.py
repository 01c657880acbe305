"""Run every benchmark (``make bench``): each ``benchmarks/bench_*.py`` module's ``main()``.

Each benchmark prints its figures and rewrites its own section of
docs/performance.md.  Pass module names to run a subset:
``python -m benchmarks.run_all calibrate diagnose``.
"""

from __future__ import annotations

import importlib
import inspect
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    names = argv if argv else sorted(p.stem[len("bench_"):] for p in
                                     Path(__file__).parent.glob("bench_*.py"))
    for name in names:
        module = importlib.import_module(f"benchmarks.bench_{name}")
        print(f"== benchmark {name}", flush=True)
        t0 = time.perf_counter()
        # each benchmark with its defaults (run_all's own arguments are not for them)
        module.main(*([[]] if inspect.signature(module.main).parameters else []))
        print(f"== {name} done in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
