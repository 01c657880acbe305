"""``hitops calibrate`` on a dask.distributed local cluster of worker processes (issue 7).

A ``distributed.LocalCluster`` of 1 and then 2 worker processes (one thread
each) is started by this script; ``hitops calibrate --method pwc --scheduler
tcp://...`` runs as its own process against it, on the paper-size pair of
bench_calibrate (8 stations, 43 200 s, 4 correlations, 1 209 600 rows per
band).  The same command without ``--scheduler`` (dask's threaded scheduler
in one process) writes the reference result into a separate copy of the
target set; the output column and FLAG of every distributed run must be
identical to it, element by element (the script raises otherwise).

Timings: whole ``hitops calibrate`` process, median of ``--repeats``; its
peak RSS is the client's; each worker's peak RSS is read from the worker
process itself (``getrusage`` through ``Client.run``).

Run: ``python -m benchmarks.bench_distributed [--workdir DIR] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from ._report import machine_line, median, replace_section, run_process
from .bench_calibrate import build


def _columns(ms: Path, names):
    from casacore import tables as pt

    with pt.table(str(ms), ack=False) as t:
        return {n: t.getcol(n) for n in names}


def _worker_peak_rss_mb():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv if argv is not None else [])
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-distributed-"))
    workdir.mkdir(parents=True, exist_ok=True)
    ref_ms, target_ms = build(workdir)
    hitops = str(Path(sys.executable).with_name("hitops"))
    load = [os.getloadavg()[0]]

    single_ms = workdir / "single.ms"
    dist_ms = workdir / "distributed.ms"
    for copy in (single_ms, dist_ms):
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(target_ms, copy)

    def command(target, *extra):
        return [hitops, "calibrate", str(ref_ms), str(target), "--method", "pwc", "--overwrite",
                "--report", str(workdir / f"{Path(target).stem}.json"), *extra]

    run_process(command(single_ms))   # warm-up (page cache, numba cache)
    single = [run_process(command(single_ms)) for _ in range(args.repeats)]
    expected = _columns(single_ms, ["PWC_DATA", "FLAG"])

    import dask
    from distributed import Client, LocalCluster

    rows = []
    checks = []
    for n_workers in (1, 2):
        # dask's scratch space in the benchmark's directory, not the machine's /tmp
        with dask.config.set({"temporary-directory": str(workdir)}), \
                LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                             dashboard_address=None) as cluster, Client(cluster) as client:
            address = cluster.scheduler_address
            cmd = command(dist_ms, "--scheduler", address)
            run_process(cmd)   # warm-up: each worker loads the numba kernels once
            runs = [run_process(cmd) for _ in range(args.repeats)]
            worker_rss = client.run(_worker_peak_rss_mb)
        got = _columns(dist_ms, ["PWC_DATA", "FLAG"])
        same = {c: bool(np.array_equal(got[c], expected[c])) for c in expected}
        checks.append((n_workers, same, float(np.abs(got["PWC_DATA"] - expected["PWC_DATA"]).max())))
        if not all(same.values()):
            raise RuntimeError(f"distributed run with {n_workers} workers differs from the "
                               f"single-process run: {same}")
        rows.append((n_workers, address, runs, worker_rss))
        print(n_workers, "workers", [r["wall_s"] for r in runs], flush=True)
    load.append(os.getloadavg()[0])

    s_wall = median([r["wall_s"] for r in single])
    lines = [f"| one process, threaded scheduler | {s_wall:.2f} | "
             f"{median([r['cpu_s'] for r in single]):.2f} | "
             f"{max(r['peak_rss_mb'] for r in single):.0f} | - |"]
    for n_workers, address, runs, worker_rss in rows:
        lines.append(
            f"| `--scheduler {address.rsplit(':', 1)[0]}:PORT`, {n_workers} worker process"
            f"{'es' if n_workers > 1 else ''} | {median([r['wall_s'] for r in runs]):.2f} | "
            f"{median([r['cpu_s'] for r in runs]):.2f} | "
            f"{max(r['peak_rss_mb'] for r in runs):.0f} | "
            + ", ".join(f"{v:.0f}" for v in worker_rss.values()) + " |")
    check_lines = "\n".join(
        f"| {n} | {'identical' if same['PWC_DATA'] else 'DIFFERENT'} | "
        f"{'identical' if same['FLAG'] else 'DIFFERENT'} | {diff:.1e} |"
        for n, same, diff in checks)
    markdown = f"""## dask.distributed: hitops calibrate on a local cluster of worker processes (issue 7)

Machine: {machine_line()}; 1-minute load average {load[0]:.1f} before and {load[1]:.1f}
after.  Pair: 8 stations, 43 200 s of 1 s, 4 correlations (1 209 600 rows per band).
A `distributed.LocalCluster` (worker processes, one thread each) is started by the
benchmark; `hitops calibrate --method pwc --scheduler tcp://127.0.0.1:PORT` is a separate
process that connects to it: the FPT kernel tasks (one per baseline batch) run in the
workers, while the calibrate process reads the columns (dask-ms, on its own threads),
matches the bands, grids each chunk, ships each baseline batch's arrays to a worker and
writes the outputs.  The table reads and writes stay in the calibrate process: a
graph of dask-ms reads sent to a cluster is unpickled by its scheduler, whose copies of
the table handles kept the table read-locked after the run (the next run's commit
then waited on them).  Wall and CPU: the `hitops calibrate` process (median of {args.repeats}, after
one warm-up run per cluster); the CPU of the workers is not in that column.

| run | wall (s) | CPU of the calibrate process (s) | its peak RSS (MB) | worker peak RSS (MB) |
|---|---|---|---|---|
{chr(10).join(lines)}

Output against the single-process run (same inputs, separate copies of the target set):

| workers | PWC_DATA | FLAG | max abs difference |
|---|---|---|---|
{check_lines}

On one machine the cluster costs time (task and data transfer between processes,
each worker loading the numba kernels); it is there so the same command scales to a
cluster whose workers see the Measurement Sets on a shared file system
(docs/hpc.md).

Run: `python -m benchmarks.bench_distributed [--workdir DIR] [--repeats N]`.
"""
    print(markdown)
    replace_section("distributed", markdown)
    if not args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)
    else:
        for copy in (single_ms, dist_ms):
            shutil.rmtree(copy, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
