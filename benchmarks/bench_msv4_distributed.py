"""``hitops calibrate REF.ps TGT.ps --scheduler`` against one process and the zarr floor (issue 37).

A hitops.testing pair (8 stations, RR LL, one channel, time order) converted by
xradio 1.3 in time chunks of ``--chunk-rows`` rows; ``hitops calibrate --method
pwc,cfpt,cwu --no-verdict`` as a process of its own: without ``--scheduler`` (this
process's threads), and with a dask LocalCluster of 1 and of 2 single-threaded worker
processes started here (a fresh cluster per configuration).  Median wall time of
``--repeats`` runs, the client's peak RSS and each worker's (``ru_maxrss`` read on
the workers after the runs); beside them the zarr floor of the same variables
(benchmarks/bench_msv4.py ``_run_floor``) and the load average before each
configuration (the machine is shared).

What the cluster runs today: each chunk's baseline batches (the transfer kernels);
the stores are read and written on the client (docs/msv4.md, "Distributed").

Run: ``python -m benchmarks.bench_msv4_distributed [--n-time N] [--repeats N]
[--workdir DIR]``; writes its section of docs/performance.md.
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

from ._report import machine_line, replace_section, run_process
from .bench_msv4 import METHODS, N_ANT, _convert, _run_floor


def _worker_peak_mb(client) -> list:
    # VmHWM, the peak of this address space: ru_maxrss is kept across exec, so a spawned
    # worker's would be this (benchmark) process's peak when it was forked
    def peak():
        with open("/proc/self/status") as status:
            kb = next(line.split()[1] for line in status if line.startswith("VmHWM:"))
        return int(kb) / 1024.0
    return sorted(client.run(peak).values())


def _runs(ref: Path, tgt: Path, chunk_rows: int, repeats: int, n_workers: int) -> dict:
    """``repeats`` runs, with a fresh LocalCluster of ``n_workers`` processes (0: none)."""
    hitops = Path(sys.executable).with_name("hitops")
    load = os.getloadavg()[0]
    cluster = client = None
    extra = []
    if n_workers:
        from distributed import Client, LocalCluster
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
        extra = ["--scheduler", cluster.scheduler_address]
    try:
        walls, rss = [], []
        for k in range(repeats):
            r = run_process([hitops, "calibrate", ref, tgt, "--method", METHODS,
                             "--chunk-rows", str(chunk_rows), "--no-verdict", "--overwrite"]
                            + extra)
            walls.append(r["wall_s"])
            rss.append(r["peak_rss_mb"])
        workers = _worker_peak_mb(client) if client else []
    finally:
        if client:
            client.close()
            cluster.close()
    return {"wall": statistics.median(walls), "walls": walls, "client_rss": max(rss),
            "workers_rss": workers, "load": load}


def bench(work: Path, n_time: int, chunk_rows: int, repeats: int) -> str:
    from hitops.testing import PairSpec, make_pair
    from hitops.testing.pairs import Storage

    pair = make_pair(work / "pair", PairSpec(n_ant=N_ANT, n_time=n_time,
                                            storage=Storage(time_order=True)))
    step = max(1, chunk_rows // (N_ANT * (N_ANT - 1) // 2))
    ref_ps, tgt_ps = work / "ref.ps.zarr", work / "tgt.ps.zarr"
    _convert(pair.ref_ms, ref_ps, "arcae", step)
    _convert(pair.target_ms, tgt_ps, "arcae", step)
    floor = _run_floor(ref_ps, tgt_ps, len(METHODS.split(",")), repeats)
    configs = {"one process (threads)": 0, "LocalCluster, 1 worker process": 1,
               "LocalCluster, 2 worker processes": 2}
    results = {name: _runs(ref_ps, tgt_ps, chunk_rows, repeats, n) for name, n in configs.items()}
    n_row = n_time * N_ANT * (N_ANT - 1) // 2
    floor_s = floor["read"] + floor["write"]
    lines = [
        f"Measured {time.strftime('%Y-%m-%d %H:%M')} on {machine_line()} (shared with other "
        f"helpers' work: load average given per row); {n_row:,} rows per band ({N_ANT} "
        f"stations, RR LL, one channel), converted in time chunks of {step} steps; "
        f"`hitops calibrate --method {METHODS} --chunk-rows {chunk_rows} --no-verdict "
        f"--overwrite`, each run a process of its own, median of {repeats}.",
        "",
        "| configuration | wall s (median; all) | x zarr floor | client peak RSS MB | "
        "worker peak RSS MB | load before |",
        "|---|---|---|---|---|---|",
        f"| zarr floor (both bands read, {len(METHODS.split(','))} groups written) | "
        f"{floor_s:.2f} | 1.00 | | | |",
    ]
    for name, r in results.items():
        lines.append(f"| {name} | {r['wall']:.2f} ({', '.join(f'{w:.2f}' for w in r['walls'])})"
                     f" | {r['wall'] / floor_s:.2f} | {r['client_rss']:.0f} | "
                     f"{', '.join(f'{m:.0f}' for m in r['workers_rss']) or '-'} | "
                     f"{r['load']:.2f} |")
    (work / "results.json").write_text(json.dumps({"floor": floor, "runs": results}, indent=1))
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--n-time", type=int, default=35_715)   # x 28 baselines = 10^6 rows
    parser.add_argument("--chunk-rows", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-msv4-dist-"))
    work.mkdir(parents=True, exist_ok=True)
    text = bench(work, args.n_time, args.chunk_rows, args.repeats)
    # another size: a section of its own after the default one's
    key = "msv4-distributed" if args.n_time == 35_715 else f"msv4-distributed-{args.n_time}"
    replace_section(key, text)
    print(text)
    if args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
