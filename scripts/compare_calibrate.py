"""Fingerprints of everything ``hitops calibrate`` writes, to show a rewrite changes nothing.

Issue 12 rebuilds calibrate's core with the promise "same outputs, byte for
byte".  This script runs one fixed matrix of calibrate calls on the packaged
demo and paper scenes and records, for every call, the SHA-256 of each column
it writes (the method columns, FLAG, FLAG_HITOPS_BACKUP) and of its JSON report
with the run-dependent entries (timings, paths) removed:

    python scripts/compare_calibrate.py record  before.json   # on the old code
    python scripts/compare_calibrate.py check   before.json   # on the new code

``check`` exits 1 and names every case and column that differs.  The matrix:
every tracker (count, smooth, antenna) x the n0 step (none, ``--offset-model
point``, ``--offset-reference-column``) x one chunk or several
(``--chunk-rows``), all three methods in one call, plus a run through a
dask.distributed scheduler.  The scenes are simulated once into ``--workdir``
(default a temporary directory) and each case works on a fresh copy of the
target set.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SCENES = ("demo", "paper")
TRACKERS = ("count", "smooth", "antenna")
#: the offset reference column: a CFPT calibration of the same data, written once per scene
OFFSET_REFERENCE = "OFFSET_REFERENCE"
#: report entries that change from run to run without the result changing
VOLATILE = {"time_s", "timings_s", "report_path", "ref_ms", "target_ms", "path"}


#: --chunk-rows of the chunked cases: several chunks in each scene
CHUNK_ROWS = {"demo": 3000, "paper": 150_000}


def cases(scene: str):
    """(name, calibrate keyword arguments) of the matrix."""
    out = []
    for tracker in TRACKERS:
        for step in ("none", "model", "reference"):
            for chunked in (False, True):
                kw = {"method": "pwc,cfpt,cwu", "tracker": tracker, "overwrite": True}
                if step == "model":
                    kw["offset_model"] = "point"
                elif step == "reference":
                    kw["offset_reference_column"] = OFFSET_REFERENCE
                if chunked:
                    kw["chunk_rows"] = CHUNK_ROWS[scene]
                out.append((f"{tracker}-{step}-{'chunked' if chunked else 'whole'}", kw))
    out.append(("count-none-scheduler", {"method": "pwc,cfpt,cwu", "tracker": "count",
                                         "overwrite": True, "scheduler": "local"}))
    return out


def simulate(scene: str, workdir: Path):
    """The scene's two sets (simulated once) and its target set with the offset reference."""
    outdir = workdir / scene
    ref, tgt = outdir / "sim-86.ms", outdir / "sim-230.ms"
    if not (tgt / "table.dat").exists():
        subprocess.run([sys.executable, "-m", "hitops.cli", "simulate", scene, "--outdir",
                        str(outdir), "--overwrite"], check=True)
        from hitops.calibrate import calibrate_flat
        calibrate_flat(str(ref), str(tgt), method="cfpt", output_column=OFFSET_REFERENCE,
                  no_verdict=True, report=str(outdir / "offset-reference.json"))
    return ref, tgt


def column_digests(ms: Path, columns) -> dict:
    from casacore import tables as pt

    digests = {}
    with pt.table(str(ms), ack=False) as t:
        present = set(t.colnames())
        for name in columns:
            if name in present:
                digests[name] = hashlib.sha256(t.getcol(name).tobytes()).hexdigest()
    return digests


def stable(report):
    """The report without the entries that change from run to run."""
    if isinstance(report, dict):
        return {k: stable(v) for k, v in report.items() if k not in VOLATILE}
    if isinstance(report, list):
        return [stable(v) for v in report]
    return report


def run_case(ref: Path, tgt: Path, kwargs: dict, workdir: Path, client_address):
    from hitops.calibrate import calibrate_flat

    # one copy path per scene: dask-ms keeps a table handle of a path open while a cluster
    # client refers to it, and a table copied to the same path later would be read through
    # that stale handle (the deleted table's rows)
    copy = tgt.parent / "case-target.ms"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(tgt, copy)
    kwargs = dict(kwargs)
    if kwargs.get("scheduler") == "local":
        kwargs["scheduler"] = client_address
    started = time.perf_counter()
    report = calibrate_flat(str(ref), str(copy), report=str(workdir / "case.json"), **kwargs)
    elapsed = time.perf_counter() - started
    digests = column_digests(copy, ["PWC_DATA", "CFPT_DATA", "CWU_DATA", "FLAG",
                                    "FLAG_HITOPS_BACKUP"])
    text = json.dumps(stable(report), sort_keys=True)
    digests["report"] = hashlib.sha256(text.encode()).hexdigest()
    shutil.rmtree(copy)
    return digests, json.loads(text), elapsed


def fingerprint(workdir: Path, scenes, only=None) -> dict:
    from dask.distributed import Client, LocalCluster

    result = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, \
            Client(cluster, set_as_default=False) as client:
        for scene in scenes:
            ref, tgt = simulate(scene, workdir)
            for name, kwargs in cases(scene):
                if only and only not in name:
                    continue
                digests, report, elapsed = run_case(ref, tgt, kwargs, workdir,
                                                    client.scheduler.address)
                result[f"{scene}/{name}"] = {"digests": digests, "report": report}
                print(f"{scene}/{name}: {elapsed:.1f} s", flush=True)
    return result


def differences(before: dict, after: dict):
    """Lines naming every case, column and report entry that differs."""
    lines = []
    for case in sorted(set(before) | set(after)):
        if case not in before or case not in after:
            lines.append(f"{case}: only in the {'new' if case in after else 'old'} run")
            continue
        old, new = before[case]["digests"], after[case]["digests"]
        for column in sorted(set(old) | set(new)):
            if column != "report" and old.get(column) != new.get(column):
                lines.append(f"{case}: column {column} differs")
        if old.get("report") != new.get("report"):
            lines.extend(f"{case}: report {path}"
                         for path in _report_paths(before[case]["report"], after[case]["report"]))
    return lines


def _report_paths(old, new, path="") -> list:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new)):
            if key not in old or key not in new:
                out.append(f"{path}/{key} {'added' if key in new else 'removed'}")
            else:
                out.extend(_report_paths(old[key], new[key], f"{path}/{key}"))
        return out
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [p for i, (a, b) in enumerate(zip(old, new)) for p in _report_paths(a, b, f"{path}[{i}]")]
    return [] if old == new else [f"{path}: {str(old)[:80]} -> {str(new)[:80]}"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("record", "check"))
    parser.add_argument("fingerprints", type=Path, help="JSON file written by record, read by check")
    parser.add_argument("--workdir", type=Path, help="keep the simulated scenes here (reused)")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--only", help="run only the cases whose name contains this")
    args = parser.parse_args(argv)
    # the runs' own log lines would bury the result
    logging.getLogger("hitops").setLevel(logging.ERROR)
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="hitops-compare-")
        args.workdir = Path(tmp.name)
    args.workdir.mkdir(parents=True, exist_ok=True)
    try:
        now = fingerprint(args.workdir, args.scenes.split(","), args.only)
    finally:
        if tmp is not None:
            tmp.cleanup()
    if args.action == "record":
        args.fingerprints.write_text(json.dumps(now, indent=1, sort_keys=True))
        print(f"recorded {len(now)} cases in {args.fingerprints}")
        return 0
    before = json.loads(args.fingerprints.read_text())
    if args.only:
        before = {k: v for k, v in before.items() if k in now}
    lines = differences(before, now)
    for line in lines:
        print(line)
    print(f"{len(now)} cases compared: {'no differences' if not lines else f'{len(lines)} differences'}")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
