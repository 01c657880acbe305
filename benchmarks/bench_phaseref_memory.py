"""Peak memory of the calibrator step (``--calibrator-field``) on a larger phaseref set.

The packaged ``phaseref`` scene (hitops/scenes/phaseref.yml), noise-free, its hour cut
into ``--integration``-s samples (5 stations, two fields), is simulated once into
``--workdir``; then ``hitops calibrate --method pwc --calibrator-field 3C273
--chunk-rows N`` runs in a fresh process per code tree, and reports

* ``step_peak_mb``: the largest Python/numpy heap the step itself holds at once above
  what it started with (tracemalloc around :func:`hitops.calibrate.phaseref.phase_reference`:
  numpy reports its buffers to tracemalloc, python-casacore's own buffers are not seen);
* ``step_s``: the step's wall time (the first of two runs, untraced; the heap is
  measured on the second, on a fresh copy of the set);
* ``rss_mb``: the whole process's peak resident memory (transfer included).

    python benchmarks/bench_phaseref_memory.py --before /path/to/old/tree

runs the old tree (its ``hitops`` package on PYTHONPATH) and this one, interleaved,
``--repeat`` times each; the numbers are printed as JSON and a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def simulate_pair(workdir: Path, integration: float, duration: float) -> Path:
    """The scene's two sets, made once: the directory holding sim-86.ms and sim-230.ms."""
    out = workdir / f"phaseref-{integration:g}s-{duration:g}s"
    if not (out / "sim-230.ms" / "table.dat").exists():
        from hitops.simulate import simulate
        from hitops.simulate.scene import load_scene_mapping

        scene = load_scene_mapping("phaseref")[0]
        scene["observation"]["integration"] = integration
        scene["observation"]["duration"] = duration
        scene["corruptions"]["noise"] = False
        shutil.rmtree(out, ignore_errors=True)
        simulate(scene, out)
    return out


def measure(pair: Path, chunk_rows: int) -> dict:
    """One calibrate run in this process (the tree on PYTHONPATH): the step's heap peak."""
    import logging
    import tracemalloc

    from casacore import tables as pt

    from hitops.calibrate import calibrate_flat, phaseref

    logging.getLogger("hitops").setLevel(logging.ERROR)
    seen = {}
    step = phaseref.phase_reference

    def traced(run, tx, cal):
        if "step_s" not in seen:    # the first run: the wall time, untraced
            started = time.perf_counter()
            try:
                return step(run, tx, cal)
            finally:
                seen["step_s"] = time.perf_counter() - started
        tracemalloc.start()         # the second: the heap (tracemalloc slows numpy down)
        base = tracemalloc.get_traced_memory()[0]
        try:
            return step(run, tx, cal)
        finally:
            seen["step_peak_mb"] = (tracemalloc.get_traced_memory()[1] - base) / 2**20
            tracemalloc.stop()

    # hitops/calibrate/visibility_source.py takes phase_reference from the package when
    # it stages, so the package's name is the one to wrap
    phaseref.phase_reference = traced
    for _ in range(2):
        with tempfile.TemporaryDirectory(prefix="bench-phaseref-") as tmp:
            tgt = Path(tmp) / "target.ms"
            shutil.copytree(pair / "sim-230.ms", tgt)
            with pt.table(str(tgt), ack=False) as t:
                n_rows = t.nrows()
            calibrate_flat(str(pair / "sim-86.ms"), str(tgt), method="pwc", no_verdict=True,
                           calibrator_field="3C273", chunk_rows=chunk_rows,
                           report=str(Path(tmp) / "report.json"))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"rows": n_rows, "step_peak_mb": round(seen["step_peak_mb"], 1),
            "step_s": round(seen["step_s"], 2),
            "rss_mb": round(rss, 1)}


def run_tree(tree: Path, pair: Path, chunk_rows: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, __file__, "--measure", str(pair), "--chunk-rows",
                          str(chunk_rows)], env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, help="the old tree to compare with")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "bench-pr")
    parser.add_argument("--integration", type=float, default=0.5)
    parser.add_argument("--duration", type=float, default=3600.0)
    parser.add_argument("--chunk-rows", type=int, default=5000)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.measure is not None:
        print(json.dumps(measure(args.measure, args.chunk_rows)))
        return 0
    args.workdir.mkdir(parents=True, exist_ok=True)
    pair = simulate_pair(args.workdir, args.integration, args.duration)
    trees = ([("before", args.before)] if args.before else []) + [("after", HERE)]
    results = {name: [] for name, _ in trees}
    for _ in range(args.repeat):
        for name, tree in trees:
            results[name].append(run_tree(tree, pair, args.chunk_rows))
    print(json.dumps(results, indent=1))
    print("| tree | target rows | --chunk-rows | step heap peak (MB) | step wall (s) "
          "| process peak RSS (MB) |")
    print("|---|---|---|---|---|---|")
    for name, runs in results.items():
        print(f"| {name} | {runs[0]['rows']} | {args.chunk_rows} | "
              f"{max(r['step_peak_mb'] for r in runs)} | {min(r['step_s'] for r in runs)} | "
              f"{max(r['rss_mb'] for r in runs)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
