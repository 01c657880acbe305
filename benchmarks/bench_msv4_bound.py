"""What one process here cannot go below: issue 37's 1.5x target at 10^7 rows, taken apart.

The target compares ``hitops calibrate`` on two processing sets of 10^7 rows with the
zarr floor: a process that starts python, imports numpy and zarr, reads both bands'
EFFECTIVE_INTEGRATION_TIME, VISIBILITY and FLAG and writes one VISIBILITY and FLAG
(:data:`benchmarks.bench_msv4._FLOOR_PROCESS`).  Any hitops run also pays two things
the floor does not, whatever its code does:

* **numba's start**: importing numba and setting up its target context before the
  first cached kernel runs (measured as a process that imports numpy, zarr and numba
  and calls one cached hitops kernel; and as one that imports what ``hitops calibrate``
  imports before its first stage);
* **the arithmetic the transfer cannot skip**: one arctangent of each reference
  sample and one sine and cosine of each target sample, in float64 (GUIDE.md
  section 1: the reference phase times a non-integer ratio), timed in this process
  as NumPy's loops and as numba scalar loops (what the kernels compile to); the
  bounds take the faster of the two for each function.

From these, two lower bounds on the wall time of any one-process run on this
machine's cores: **serial start** (nothing of the floor's work overlaps numba's start:
start + (floor CPU - floor start CPU + arithmetic) / cores), and **overlapped start**
(numba starts while the reads run, every core busy throughout: (numba start CPU + the
floor's CPU after its start + arithmetic) / cores).  Beside them, the floor with
numba's start on a thread of its own (how much of the start really hides behind
zarr's reads here), and ``hitops calibrate --method pwc`` as a user runs it.

The bounds count only the arithmetic; **the least PWC program**
(:mod:`benchmarks.least_pwc`) is the method itself done with nothing else: the floor's
reads and writes in chunks, NumPy's arctangent and one fused numba kernel, no checks,
no pairing, no staging, no report.  Its output is compared with the data group the
pwc run writes (equal to float32 rounding, flags identical, on this pair), and it takes
turns with the floor and the run, so that the three see the same hours of the machine.

Run: ``python -m benchmarks.bench_msv4_bound [--workdir DIR] [--n-time 357150]
[--repeats 5]`` (about 4 minutes here, one of them building the pair; a pair already in
``--workdir`` is reused); writes the ``msv4-bound`` section of docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ._report import load_line, machine_line, replace_section, run_process
from .bench_msv4 import _FLOOR_PROCESS, _floor_arrays_removed

#: where ``python -m benchmarks.least_pwc`` finds its package
_REPO = Path(__file__).resolve().parents[1]

#: the floor process's start: what it has before its first read
_START = "import numpy, zarr"
#: the same with numba's start: one cached hitops kernel called
_KERNEL = ("from hitops.kernels.cells import count_marked; "
           "count_marked(numpy.zeros(0, numpy.int64), numpy.zeros(0, numpy.bool_))")
_START_NUMBA = f"import numpy, zarr, numba; {_KERNEL}"
#: what hitops calibrate imports before its first stage, and one kernel
_START_HITOPS = ("import numpy, zarr; import hitops.cli, hitops.calibrate.api, "
                 f"hitops.calibrate.pipeline, hitops.calibrate.passes; {_KERNEL}")
#: the floor with numba's start on a thread beside its reads and writes
_FLOOR_BESIDE_NUMBA = (
    "import threading\n"
    "def _numba_start():\n"
    "    import numpy\n"
    f"    {_KERNEL}\n"
    "_beside = threading.Thread(target=_numba_start)\n"
    "_beside.start()\n"
    + _FLOOR_PROCESS + "\n_beside.join()\n")


#: ``hitops calibrate`` in a process that samples its threads' CPU time (Linux
#: /proc/self/task/*/stat, every 0.1 s) and prints the last sample of each thread,
#: summed by the name of its pool (hitops-transfer_0 and _1 -> hitops-transfer), as JSON
_THREAD_CPU = r"""
import json, os, sys, threading, time
tick = os.sysconf("SC_CLK_TCK")
last = {}
def sample():
    while True:
        names = {t.native_id: t.name for t in threading.enumerate()}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            name = names.get(int(tid), last.get(tid, ("other", 0))[0])
            last[tid] = (name, (int(fields[11]) + int(fields[12])) / tick)
        time.sleep(0.1)
threading.Thread(target=sample, daemon=True, name="sampler").start()
from hitops.cli import main
sys.argv = ["hitops"] + sys.argv[2:]
try:
    main()
except SystemExit as done:
    if done.code:
        raise
time.sleep(0.15)
totals = {}
for name, seconds in last.values():
    pool = name.rsplit("_", 1)[0] if name[-1:].isdigit() else name
    totals[pool] = totals.get(pool, 0.0) + seconds
with open(os.environ["THREAD_CPU_OUT"], "w") as f:
    json.dump(totals, f)
"""


def _thread_cpu(ref: Path, tgt: Path, work: Path) -> dict:
    """CPU seconds of each thread pool of one ``hitops calibrate --method pwc`` run (the
    sampler's own share included under "sampler")."""
    out = work / "thread-cpu.json"
    run_process([sys.executable, "-c", _THREAD_CPU, "-", "calibrate", ref, tgt, "--method",
                 "pwc", "--no-verdict", "--overwrite"], env={"THREAD_CPU_OUT": str(out)})
    return json.loads(out.read_text())


def _summary(runs) -> dict:
    """Median wall and CPU of processes run by ``run_process``, and every wall."""
    return {"wall": statistics.median(r["wall_s"] for r in runs),
            "cpu": statistics.median(r["cpu_s"] for r in runs),
            "walls": [r["wall_s"] for r in runs]}


def _processes(script: str, args, repeats: int, store: Path = None) -> dict:
    """Median wall and CPU of ``repeats`` runs of ``python -c script args``; a floor's
    arrays are taken off ``store`` after each run."""
    runs = []
    for k in range(repeats):
        if store is None:
            runs.append(run_process([sys.executable, "-c", script, *args]))
        else:
            with _floor_arrays_removed(store):
                runs.append(run_process([sys.executable, "-c", script, *args, f"B{k}"]))
    return _summary(runs)


def _least_check(ref: Path, tgt: Path) -> dict:
    """benchmarks/least_pwc.py run once (its kernel compiled into numba's cache, so the
    timed runs load it as hitops's are loaded) and its output compared with the data
    group the last ``hitops calibrate --method pwc`` left in ``tgt``."""
    from .least_pwc import compare

    with _floor_arrays_removed(tgt):
        run_process([sys.executable, "-m", "benchmarks.least_pwc", ref, tgt, "CHECK"],
                    cwd=_REPO)
        return compare(tgt, "CHECK")


def _alternating(ref: Path, tgt: Path, repeats: int) -> dict:
    """The floor, the least PWC program and ``hitops calibrate --method pwc`` (default
    chunks, --overwrite), each ``repeats`` times in turn, so that all three see the same
    hours of the machine: median wall and CPU of each.  ``hitops calibrate`` runs once
    before (its first run may create the data group: not a rerun) and the least program
    is checked against what that run wrote (:func:`_least_check`)."""
    hitops = Path(sys.executable).with_name("hitops")
    calibrate = [hitops, "calibrate", ref, tgt, "--method", "pwc", "--no-verdict",
                 "--overwrite"]
    run_process(calibrate)
    check = _least_check(ref, tgt)
    runs = {"floor": [], "least": [], "run": []}
    for k in range(repeats):
        with _floor_arrays_removed(tgt):
            runs["floor"].append(run_process([sys.executable, "-c", _FLOOR_PROCESS, ref, tgt,
                                              1, f"F{k}"]))
        with _floor_arrays_removed(tgt):
            runs["least"].append(run_process([sys.executable, "-m", "benchmarks.least_pwc",
                                              ref, tgt, f"L{k}"], cwd=_REPO))
        runs["run"].append(run_process(calibrate))
    out = {name: _summary(done) for name, done in runs.items()}
    out["least"]["check"] = check
    return out


def _arithmetic(n_samples: int, repeats: int) -> dict:
    """CPU seconds of ``n_samples`` float64 arctangents and of as many sine-cosine pairs,
    as NumPy's vector loops and as numba scalar loops (blocks of 10^6, warm)."""
    import numba

    @numba.njit(nogil=True)
    def scalar_atan2(y, x, out):
        for i in range(y.size):
            out[i] = np.arctan2(y[i], x[i])

    @numba.njit(nogil=True)
    def scalar_phasor(theta, out):
        for i in range(theta.size):
            out[i] = complex(np.cos(theta[i]), np.sin(theta[i]))

    rng = np.random.default_rng(0)
    block = 1_000_000
    y, x = rng.normal(size=block), rng.normal(size=block)
    theta = rng.uniform(-np.pi, np.pi, block)
    phase, phasor = np.empty(block), np.empty(block, np.complex128)
    cosine, sine = np.empty(block), np.empty(block)
    scalar_atan2(y, x, phase)
    scalar_phasor(theta, phasor)
    # every way writes into arrays made once (a new array per call would time page faults)
    ways = {
        "numpy_atan2": lambda: np.arctan2(y, x, out=phase),
        "numpy_sincos": lambda: (np.cos(theta, out=cosine), np.sin(theta, out=sine)),
        "numba_atan2": lambda: scalar_atan2(y, x, phase),
        "numba_sincos": lambda: scalar_phasor(theta, phasor),
    }
    per_sample = {}
    for name, way in ways.items():
        way()
        runs = []
        for _ in range(repeats):
            start = time.process_time()
            way()
            runs.append((time.process_time() - start) / block)
        per_sample[name] = statistics.median(runs)
    return {name: s * n_samples for name, s in per_sample.items()} | {
        f"{name}_ns": s * 1e9 for name, s in per_sample.items()}


def bench(work: Path, n_time: int, repeats: int) -> str:
    from .bench_msv4_distributed import _one_channel_pair

    ref, tgt = work / "ref.ps.zarr", work / "tgt.ps.zarr"
    n_row = n_time * 28
    pair_text = f"{n_row:,} rows per band (8 stations, RR LL, one channel)"
    if not (ref.is_dir() and tgt.is_dir()):     # a pair left by an earlier run is reused
        ref, tgt, pair_text = _one_channel_pair(work, n_time, 100_000)
        shutil.rmtree(work / "pair", ignore_errors=True)     # the v2 sets: not read here
    n_cores = os.cpu_count() or 1
    start = _processes(_START, [], repeats)
    start_numba = _processes(_START_NUMBA, [], repeats)
    start_hitops = _processes(_START_HITOPS, [], repeats)
    beside = _processes(_FLOOR_BESIDE_NUMBA, [ref, tgt, 1], repeats, tgt)
    turns = _alternating(ref, tgt, repeats)
    floor, least, run = turns["floor"], turns["least"], turns["run"]
    threads = _thread_cpu(ref, tgt, work)
    n_samples = 2 * n_row                 # RR LL of every row, each band
    math = _arithmetic(n_samples, repeats)
    # the faster way of each (NumPy's arctangent is a vector loop here, its sine and
    # cosine are not)
    arithmetic = (min(math["numpy_atan2"], math["numba_atan2"])
                  + min(math["numpy_sincos"], math["numba_sincos"]))
    io_cpu = floor["cpu"] - start["cpu"]
    serial = start_numba["wall"] + (io_cpu + arithmetic) / n_cores
    overlapped = (start_numba["cpu"] + io_cpu + arithmetic) / n_cores
    target = 1.5 * floor["wall"]

    def row(name, r):
        return (f"| {name} | {r['wall']:.2f} ({', '.join(f'{w:.2f}' for w in r['walls'])}) | "
                f"{r['cpu']:.2f} | {r['wall'] / floor['wall']:.2f} |")

    lines = [
        f"Measured {time.strftime('%Y-%m-%d %H:%M')} on {machine_line()}, {load_line()}; "
        f"{pair_text}; each row a process of its own, median of {repeats}.",
        "",
        "| process | wall s (median; all) | CPU s | x floor |",
        "|---|---|---|---|",
        row("python, numpy and zarr imported (the floor's start)", start),
        row("the same, numba imported and one cached hitops kernel called", start_numba),
        row("the same with what `hitops calibrate` imports before its first stage",
            start_hitops),
        row("**the zarr floor** (its start, both bands read, one group written)", floor),
        row("the floor with numba's start on a thread beside it", beside),
        row("**the least PWC program** (benchmarks/least_pwc.py: the floor's reads and "
            "writes in chunks, one numba kernel)", least),
        row("`hitops calibrate --method pwc --no-verdict --overwrite` (default chunks)", run),
        "",
        f"The floor, the least PWC program and the run took turns ({repeats} rounds).  The "
        "least program's output against the data group `hitops calibrate --method pwc` "
        f"wrote: at most {least['check']['max_relative']:.1e} of the amplitude apart, flags "
        + ("identical" if least['check']['same_flags'] else "**different**")
        + f"; the run took {run['wall'] / least['wall']:.2f}x the least program's wall.",
        "",
        f"The arithmetic of {n_samples:,} samples per band, CPU seconds (ns per sample): "
        f"arctangent {math['numpy_atan2']:.2f} ({math['numpy_atan2_ns']:.1f}) in NumPy, "
        f"{math['numba_atan2']:.2f} ({math['numba_atan2_ns']:.1f}) in a numba loop; sine "
        f"and cosine {math['numpy_sincos']:.2f} ({math['numpy_sincos_ns']:.1f}) in NumPy, "
        f"{math['numba_sincos']:.2f} ({math['numba_sincos_ns']:.1f}) in a numba loop.",
        "",
        f"| lower bound on {n_cores} cores (the faster way of each function) | wall s | x floor |",
        "|---|---|---|",
        f"| serial start: numba's start, then the floor's I/O CPU "
        f"({io_cpu:.2f} s) and the arithmetic ({arithmetic:.2f} s) on every core | "
        f"{serial:.2f} | {serial / floor['wall']:.2f} |",
        f"| overlapped start: numba's start CPU ({start_numba['cpu']:.2f} s), the I/O and the "
        f"arithmetic, every core busy from the first instant | {overlapped:.2f} | "
        f"{overlapped / floor['wall']:.2f} |",
        f"| the least PWC program, measured (above) | {least['wall']:.2f} | "
        f"{least['wall'] / floor['wall']:.2f} |",
        f"| issue 37's target, 1.5 x the floor | {target:.2f} | 1.50 |",
        "",
        "Where one `hitops calibrate --method pwc` run's CPU went, by thread (sampled every "
        "0.1 s from /proc; zarr's event loop is `zarr_io`, its codec threads `asyncio`): "
        + ", ".join(f"{name} {seconds:.2f} s" for name, seconds in
                    sorted(threads.items(), key=lambda kv: -kv[1]) if seconds >= 0.01)
        + f"; {sum(threads.values()):.2f} s in all.",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--n-time", type=int, default=357_150)   # x 28 baselines: 10^7 rows
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-msv4-bound-"))
    work.mkdir(parents=True, exist_ok=True)
    text = bench(work, args.n_time, args.repeats)
    replace_section("msv4-bound", text)
    print(text)
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
