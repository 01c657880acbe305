"""arcae (ratt-ru's Arrow bindings for casacore) against python-casacore on calibrate's reads (issue 28).

arcae releases the GIL in every call and reads rows given as an index array in
any order; python-casacore holds the GIL and reads row ranges (getcol) or a row
selection (selectrows).  Measured here, in one process per reader, on a
hitops.testing pair of 10^6 rows (8 stations, 4 correlations, one channel,
stored baseline by baseline as make_pair writes it), page cache warm, median of
``--repeats`` calls each:

* the columns calibrate reads (TIME, ANTENNA1, ANTENNA2, DATA, FLAG), whole, in
  storage order: python-casacore ``getcol`` against arcae ``getcol``;
* two correlations of DATA (RR, LL): ``getcolslice`` against an index on the
  correlation axis;
* one time chunk of 10^5 rows in time order from the baseline-major table: the
  runs-and-permute reader calibrate uses (hitops/io/time_sorted.py, one getcol per
  run of rows, then the rows put in time order) against arcae ``getcol`` with the
  chunk's row numbers in time order as its index;
* the five columns read on two threads at once (arcae without the GIL) against one
  thread.

arcae is not part of the project's environment (it pins pyarrow exactly and needs
numpy >= 2 and Python >= 3.11): give an interpreter that has it with
``--arcae-python`` (e.g. a throwaway venv with ``pip install arcae python-casacore
numpy``).  Without one that imports arcae the arcae rows are skipped, and the
section says so.

Run: ``python -m benchmarks.bench_arcae [--arcae-python PATH] [--workdir DIR] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

COLUMNS = ["TIME", "ANTENNA1", "ANTENNA2", "DATA", "FLAG"]
N_TIME = 35_715          # x 28 baselines = 1,000,020 rows
CHUNK_ROWS = 100_000

# The measuring side: run in the interpreter under test (numpy, python-casacore and, for
# the arcae rows, arcae); it imports nothing of hitops.
_MEASURE = r'''
import json, statistics, sys, threading, time
import numpy as np
from casacore import tables as pt

ms, which, repeats = sys.argv[1], sys.argv[2], int(sys.argv[3])
columns = ["TIME", "ANTENNA1", "ANTENNA2", "DATA", "FLAG"]
chunk = np.load(sys.argv[4])          # row numbers of one time chunk, in time order

def timed(fn):
    fn()                               # warm: page cache, first-call costs
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter(); fn(); runs.append(time.perf_counter() - t0)
    return statistics.median(runs)

def two_threads(read_one):
    def go():
        threads = [threading.Thread(target=lambda cs=cs: [read_one(c) for c in cs])
                   for cs in (["DATA", "TIME"], ["FLAG", "ANTENNA1", "ANTENNA2"])]
        [t.start() for t in threads]; [t.join() for t in threads]
    return go

out = {}
if which == "casacore":
    t = pt.table(ms, ack=False)
    out["whole"] = timed(lambda: [t.getcol(c) for c in columns])
    out["corr_slice"] = timed(lambda: t.getcolslice("DATA", [0, 0], [0, 3], [1, 3]))
    asc = np.sort(chunk)
    place = np.searchsorted(asc, chunk)
    breaks = np.flatnonzero(np.diff(asc) != 1) + 1
    starts, stops = np.r_[0, breaks], np.r_[breaks, asc.size]
    def runs_then_permute():
        for c in columns:
            parts = [t.getcol(c, int(asc[a]), int(b - a)) for a, b in zip(starts, stops)]
            np.concatenate(parts)[place]
    out["chunk_time_order"] = timed(runs_then_permute)
    out["chunk_runs"] = int(starts.size)
    out["two_threads"] = timed(two_threads(lambda c: t.getcol(c)))
else:
    import arcae
    t = arcae.table(ms)
    def get(c, index=None):
        return np.asarray(t.getcol(c, index=index) if index is not None else t.getcol(c))
    out["whole"] = timed(lambda: [get(c) for c in columns])
    rows = np.arange(t.nrow(), dtype=np.int64)
    out["corr_slice"] = timed(lambda: get("DATA", (rows, None, np.array([0, 3], np.int64))))
    out["chunk_time_order"] = timed(lambda: [get(c, (chunk,)) for c in columns])
    out["two_threads"] = timed(two_threads(lambda c: get(c)))
    out["version"] = arcae.__version__
# the values agree with python-casacore's (same cells, same order)
ref = pt.table(ms, ack=False)
got = get("DATA", (chunk,)) if which == "arcae" else None
out["same_values"] = bool(got is None or np.array_equal(
    got, ref.getcol("DATA")[chunk]))
print(json.dumps(out))
'''


def build(workdir: Path) -> Path:
    """The 10^6-row pair's target set (baseline-major) and one time chunk's rows."""
    import numpy as np
    from casacore import tables as pt

    from hitops.testing import PairSpec, make_pair

    pair = workdir / "pair"
    if not (pair / "target.ms").exists():
        shutil.rmtree(pair, ignore_errors=True)
        make_pair(pair, PairSpec(n_ant=8, n_time=N_TIME, corr_types=("RR", "RL", "LR", "LL"),
                                 seed=2))
    with pt.table(str(pair / "target.ms"), ack=False) as t:
        time = t.getcol("TIME")
    order = np.argsort(time, kind="stable")          # dask-ms's ORDERBY TIME order
    middle = order.size // 2
    np.save(workdir / "chunk.npy", order[middle:middle + CHUNK_ROWS].astype(np.int64))
    return pair / "target.ms"


def has_arcae(python: str) -> bool:
    return subprocess.run([python, "-c", "import arcae"], capture_output=True).returncode == 0


def measure(python: str, which: str, ms: Path, workdir: Path, repeats: int) -> dict:
    script = workdir / "measure_reads.py"
    script.write_text(_MEASURE)
    done = subprocess.run([python, str(script), str(ms), which, str(repeats),
                           str(workdir / "chunk.npy")], capture_output=True, text=True,
                          check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def versions(python: str) -> dict:
    code = ("import importlib.metadata as m, json, sys; "
            "print(json.dumps({p: (m.version(p) if any(True for _ in m.distributions(name=p)) "
            "else None) for p in sys.argv[1:]}))")
    got = subprocess.run([python, "-c", code, "arcae", "numpy", "pyarrow", "python-casacore",
                          "dask", "dask-ms"], capture_output=True, text=True, check=True)
    return json.loads(got.stdout)


def render(pc: dict, ar: dict | None, ours: dict, theirs: dict | None, load) -> str:
    from ._report import machine_line

    def row(label, key, unit="s"):
        a = f"{ar[key]:.3f}" if ar else "not measured (arcae absent)"
        ratio = f"{pc[key] / ar[key]:.2f}x" if ar else "-"
        return f"| {label} | {pc[key]:.3f} | {a} | {ratio} |"

    pins = ", ".join(f"{k} {v}" for k, v in ours.items() if v) if ours else "-"
    arc = ", ".join(f"{k} {v}" for k, v in theirs.items() if v) if theirs else "arcae absent"
    return f"""## arcae against python-casacore (issue 28)

Machine: {machine_line()}; 1-minute load average {load[0]:.1f} before and {load[1]:.1f}
after (shared machine: wall times are upper bounds).  A hitops.testing pair of
1,000,020 rows (8 stations, 4 correlations, one channel, stored baseline by
baseline); each reader in its own process, page cache warm, median of the repeated
calls (benchmarks/bench_arcae.py).  Environments: the project's ({pins}); the
throwaway one with arcae ({arc}).

| read | python-casacore (s) | arcae (s) | python-casacore / arcae |
|---|---|---|---|
{row("TIME, ANTENNA1, ANTENNA2, DATA, FLAG, whole, storage order", "whole")}
{row("DATA, two of four correlations (getcolslice / index)", "corr_slice")}
{row(f"one time chunk of {CHUNK_ROWS:,} rows in time order, five columns ({pc['chunk_runs']} row runs; runs then permute / index array)", "chunk_time_order")}
{row("the five columns on two threads at once", "two_threads")}

Values: arcae's DATA at the chunk's rows equals python-casacore's
({"checked, identical" if ar and ar["same_values"] else "not checked"}).
"""


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arcae-python", default=sys.executable,
                        help="an interpreter with arcae, numpy and python-casacore")
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv if argv is not None else sys.argv[1:])
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-arcae-"))
    workdir.mkdir(parents=True, exist_ok=True)
    load = [os.getloadavg()[0]]
    ms = build(workdir)
    pc = measure(sys.executable, "casacore", ms, workdir, args.repeats)
    ar = theirs = None
    if has_arcae(args.arcae_python):
        ar = measure(args.arcae_python, "arcae", ms, workdir, args.repeats)
        theirs = versions(args.arcae_python)
    else:
        print(f"arcae is not importable by {args.arcae_python}: its rows are skipped "
              "(give --arcae-python)", file=sys.stderr)
    load.append(os.getloadavg()[0])
    (workdir / "arcae-results.json").write_text(json.dumps(
        {"casacore": pc, "arcae": ar, "ours": versions(sys.executable), "theirs": theirs,
         "load": load}, indent=1))
    markdown = render(pc, ar, versions(sys.executable), theirs, load)
    print(markdown)
    if ar is not None:   # a section without arcae's numbers would say nothing
        from ._report import replace_section
        replace_section("arcae", markdown)
    if not args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
