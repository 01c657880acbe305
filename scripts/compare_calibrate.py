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

``--scenes table`` runs the ``--reference-table`` path (not in the default
scenes; its own fingerprint file): a pair laid out by casatools.simulator
(tests/solutions_scene.py, two fields in alternating scans), solved by real CASA
fringefit (4 s) and gaincal (G Jones, solint 'int'); cases: pwc, pwc,cfpt, the n0
step (``--offset-model point``, ``--offset-reference-column``), ``--caltable``,
one chunk or several.  Besides the columns and FLAG it digests the written
caltable's FPARAM, FLAG and row axes.

``--scenes phaseref`` runs the ``--calibrator-field`` step (its own fingerprint file): the
casatools.simulator pair of tests/test_sfpr.py (15 min, 60-s slews, a resolved calibrator
in MODEL_DATA), the packaged ``phaseref`` scene cut to 20 min, and that with one 230-GHz
channel (the count carried across the switches); the count and antenna trackers, one
chunk or several.  ``--only`` matches ``scene/case``.
"""

from __future__ import annotations

import argparse
import contextlib
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
#: the --reference-table scene: run with --scenes table
TABLE_SCENE = "table"
#: the --calibrator-field scenes: run with --scenes phaseref
PHASEREF_SCENE = "phaseref"
#: the packaged phaseref scene's duration in the phaseref cases (s): cut to 20 min
PHASEREF_PACKAGED_S = 1200
TRACKERS = ("count", "smooth", "antenna")
#: the offset reference column: a CFPT calibration of the same data, written once per scene
OFFSET_REFERENCE = "OFFSET_REFERENCE"
#: report entries that change from run to run without the result changing
VOLATILE = {"time_s", "timings_s", "report_path", "ref_ms", "target_ms", "path"}


#: --chunk-rows of the chunked cases: several chunks in each scene
CHUNK_ROWS = {"demo": 3000, "paper": 150_000, TABLE_SCENE: 500, PHASEREF_SCENE: 150}
#: the table scene's scans: (field, start s, stop s), two fields alternating
TABLE_SCANS = (("M87", 0.0, 60.0), ("3C273", 70.0, 130.0), ("M87", 140.0, 200.0),
               ("3C273", 210.0, 270.0))
#: the table scene's solution tables (written once per scene) and what solves them
TABLES = ("fringe", "gain", "flagged")
#: columns whose digests each case records
COLUMNS = ["PWC_DATA", "CFPT_DATA", "CWU_DATA", "FLAG", "FLAG_HITOPS_BACKUP"]
#: the written --caltable's columns whose digests a table case records
CALTABLE_COLUMNS = ["TIME", "FIELD_ID", "SPECTRAL_WINDOW_ID", "ANTENNA1", "ANTENNA2", "FPARAM",
                    "FLAG"]


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


def table_cases():
    """(name, calibrate keyword arguments) of the --reference-table matrix; the table is
    named by its entry of TABLES and ``caltable`` True asks for a written table."""
    chunk = {"chunk_rows": CHUNK_ROWS[TABLE_SCENE]}
    rows = [
        ("fringe-pwc-whole", {"table": "fringe", "method": "pwc"}),
        ("fringe-pwc,cfpt-caltable-whole", {"table": "fringe", "method": "pwc,cfpt",
                                            "caltable": True}),
        ("fringe-pwc,cfpt-caltable-chunked", {"table": "fringe", "method": "pwc,cfpt",
                                              "caltable": True, **chunk}),
        ("fringe-cfpt-chunked", {"table": "fringe", "method": "cfpt", **chunk}),
        ("fringe-model-caltable-whole", {"table": "fringe", "method": "pwc",
                                         "offset_model": "point", "caltable": True}),
        ("fringe-model-caltable-chunked", {"table": "fringe", "method": "pwc,cfpt",
                                           "offset_model": "point", "caltable": True, **chunk}),
        ("fringe-reference-chunked", {"table": "fringe", "method": "pwc",
                                      "offset_reference_column": "MODEL_DATA", **chunk}),
        ("gain-pwc,cfpt-caltable-whole", {"table": "gain", "method": "pwc,cfpt",
                                          "caltable": True}),
        ("gain-model-caltable-chunked", {"table": "gain", "method": "pwc",
                                         "offset_model": "point", "caltable": True, **chunk}),
        ("flagged-pwc,cfpt-caltable-chunked", {"table": "flagged", "method": "pwc,cfpt",
                                               "caltable": True, **chunk}),
        ("flagged-model-whole", {"table": "flagged", "method": "pwc", "offset_model": "point"}),
    ]
    return [(name, {"overwrite": True, **kw}) for name, kw in rows]


def phaseref_cases():
    """(name, calibrate keyword arguments) of the --calibrator-field matrix; ``pair`` names
    the pair: "sfpr" (tests/test_sfpr.py's casatools.simulator pair, 15 min, 60-s slews,
    a resolved calibrator in MODEL_DATA), "packaged" (the phaseref scene cut to 20 min) or
    "onechan" (that with one 230-GHz channel, noise-free: the count carried across the
    switches)."""
    chunk = {"chunk_rows": CHUNK_ROWS[PHASEREF_SCENE]}
    sfpr = {"pair": "sfpr", "calibrator_field": "CAL", "ref_model_column": "MODEL_DATA"}
    # the packaged scene's calibrator is resolved: its model in both bands (check_model)
    packaged = {"pair": "packaged", "calibrator_field": "3C273",
                "ref_model_column": "MODEL_DATA"}
    rows = [
        ("sfpr-count-whole", {**sfpr, "method": "pwc"}),
        ("sfpr-count-chunked", {**sfpr, "method": "pwc", **chunk}),
        ("sfpr-antenna-whole", {**sfpr, "method": "pwc", "tracker": "antenna"}),
        ("sfpr-antenna-chunked", {**sfpr, "method": "pwc", "tracker": "antenna", **chunk}),
        ("sfpr-point-chunked", {**sfpr, "method": "pwc", "calibrator_model_column": "point",
                                "ref_model_column": None, **chunk}),
        ("packaged-count-whole", {**packaged, "method": "pwc"}),
        ("packaged-count-chunked", {**packaged, "method": "pwc", **chunk}),
        ("packaged-antenna-chunked", {**packaged, "method": "pwc", "tracker": "antenna",
                                      **chunk}),
        ("onechan-count-whole", {**packaged, "pair": "onechan", "method": "pwc,cfpt"}),
        ("onechan-count-chunked", {**packaged, "pair": "onechan", "method": "pwc,cfpt",
                                   **chunk}),
    ]
    out = []
    for name, kw in rows:
        kw = {k: v for k, v in kw.items() if v is not None}
        out.append((name, {"overwrite": True, "no_verdict": True, **kw}))
    return out


def simulate_phaseref_scene(workdir: Path):
    """The phaseref scene's two pairs, made once: {"sfpr": (ref, tgt), "packaged": (ref, tgt)}."""
    outdir = workdir / PHASEREF_SCENE
    sfpr, packaged = outdir / "sfpr", outdir / "packaged"
    if not (sfpr / "target.ms" / "table.dat").exists():
        from hitops.testing.phaseref_scene import PhaserefSpec, make_phaseref_pair

        shutil.rmtree(sfpr, ignore_errors=True)
        make_phaseref_pair(sfpr, PhaserefSpec(slew_s=60.0, duration_s=900.0))
    if not (packaged / "sim-230.ms" / "table.dat").exists():
        subprocess.run([sys.executable, "-m", "hitops.cli", "simulate", PHASEREF_SCENE,
                        "--outdir", str(packaged), "--duration", str(PHASEREF_PACKAGED_S),
                        "--overwrite"], check=True)
    onechan = outdir / "onechan"
    if not (onechan / "sim-230.ms" / "table.dat").exists():
        from hitops.simulate import simulate as simulate_scene
        from hitops.simulate.scene import load_scene_mapping

        scene = load_scene_mapping(PHASEREF_SCENE)[0]
        scene["observation"]["duration"] = PHASEREF_PACKAGED_S
        scene["corruptions"]["noise"] = False
        scene["bands"][1]["n_chan"] = 1
        shutil.rmtree(onechan, ignore_errors=True)
        simulate_scene(scene, onechan)
    return {"sfpr": (sfpr / "ref.ms", sfpr / "target.ms"),
            "packaged": (packaged / "sim-86.ms", packaged / "sim-230.ms"),
            "onechan": (onechan / "sim-86.ms", onechan / "sim-230.ms")}


def simulate_table_scene(workdir: Path):
    """The table scene's two sets and its solution tables, made once: (ref, tgt, {name: table})."""
    outdir = workdir / TABLE_SCENE
    tables = {name: outdir / f"ref.{name}" for name in TABLES}
    ref, tgt = outdir / "ref.ms", outdir / "target.ms"
    if not all((t / "table.dat").exists() for t in tables.values()):
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from solutions_scene import make_solution_pair

        from hitops.casa.tasks import fringefit, gaincal

        shutil.rmtree(outdir, ignore_errors=True)
        make_solution_pair(outdir, seed=5, scans=TABLE_SCANS)
        fringefit(str(ref), str(tables["fringe"]), solint="4s", refant="PV,PB", minsnr=3.0)
        gaincal(str(ref), str(tables["gain"]), solint="int", refant="PV,PB", calmode="p",
                minsnr=3.0, minblperant=2)
        _flag_some(tgt, tables["fringe"], tables["flagged"])
    return ref, tgt, tables


def _flag_some(tgt: Path, fringe: Path, flagged: Path) -> None:
    """Samples the table path leaves uncalibrated or finds flagged: FLAG set on the target's
    PV-PB rows in the first 20 s; a copy of the fringefit table with GL's (antenna 3)
    solutions flagged from the third scan on."""
    from casacore import tables as pt

    with pt.table(str(tgt), readonly=False, ack=False) as t:
        time, flag = t.getcol("TIME"), t.getcol("FLAG")
        rows = (t.getcol("ANTENNA1") == 0) & (t.getcol("ANTENNA2") == 1) & (time < time.min() + 20)
        flag[rows] = True
        t.putcol("FLAG", flag)
    shutil.copytree(fringe, flagged)
    with pt.table(str(flagged), readonly=False, ack=False) as t:
        time, flag = t.getcol("TIME"), t.getcol("FLAG")
        flag[(t.getcol("ANTENNA1") == 3) & (time > time.min() + TABLE_SCANS[2][1])] = True
        t.putcol("FLAG", flag)


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


def column_digests(ms: Path, columns, prefix: str = "") -> dict:
    from casacore import tables as pt

    digests = {}
    with pt.table(str(ms), ack=False) as t:
        present = set(t.colnames())
        for name in columns:
            if name in present:
                digests[prefix + name] = hashlib.sha256(t.getcol(name).tobytes()).hexdigest()
    return digests


def stable(report):
    """The report without the entries that change from run to run."""
    if isinstance(report, dict):
        return {k: stable(v) for k, v in report.items() if k not in VOLATILE}
    if isinstance(report, list):
        return [stable(v) for v in report]
    return report


def run_case(ref: Path, tgt: Path, kwargs: dict, workdir: Path, scheduler, tables=None):
    from hitops.calibrate import calibrate_flat

    # one copy path per scene: dask-ms keeps a table handle of a path open while a cluster
    # client refers to it, and a table copied to the same path later would be read through
    # that stale handle (the deleted table's rows)
    copy = tgt.parent / "case-target.ms"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(tgt, copy)
    kwargs = dict(kwargs)
    if kwargs.get("scheduler") == "local":
        kwargs["scheduler"] = scheduler()
    if "table" in kwargs:
        kwargs["reference_table"] = str(tables[kwargs.pop("table")])
    caltable = workdir / "case.caltable"
    shutil.rmtree(caltable, ignore_errors=True)
    if kwargs.pop("caltable", False):
        kwargs["caltable"] = str(caltable)
    started = time.perf_counter()
    report = calibrate_flat(str(ref), str(copy), report=str(workdir / "case.json"), **kwargs)
    elapsed = time.perf_counter() - started
    digests = column_digests(copy, COLUMNS)
    if "caltable" in kwargs:
        digests.update(column_digests(caltable, CALTABLE_COLUMNS, prefix="caltable:"))
        shutil.rmtree(caltable)
    text = json.dumps(stable(report), sort_keys=True)
    digests["report"] = hashlib.sha256(text.encode()).hexdigest()
    shutil.rmtree(copy)
    return digests, json.loads(text), elapsed


class LocalScheduler:
    """A local dask cluster, started for the first case that asks for one (the table scene
    needs none), closed with the run."""

    def __init__(self, stack: contextlib.ExitStack, workdir: Path):
        self.stack, self.address, self.workdir = stack, None, workdir

    def __call__(self) -> str:
        if self.address is None:
            import dask
            from dask.distributed import Client, LocalCluster

            # dask's scratch space (the scheduler's and the workers') in the work
            # directory, not the machine's /tmp
            self.stack.enter_context(dask.config.set({"temporary-directory": str(self.workdir)}))
            cluster = self.stack.enter_context(LocalCluster(
                n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None))
            client = self.stack.enter_context(Client(cluster, set_as_default=False))
            self.address = client.scheduler.address
        return self.address


def fingerprint(workdir: Path, scenes, only=None) -> dict:
    result = {}
    with contextlib.ExitStack() as stack:
        scheduler = LocalScheduler(stack, workdir)
        for scene in scenes:
            matrix = {TABLE_SCENE: table_cases, PHASEREF_SCENE: phaseref_cases}
            selected = [(name, kw) for name, kw in
                        (matrix[scene]() if scene in matrix else cases(scene))
                        if not only or only in f"{scene}/{name}"]
            if not selected:
                continue
            pairs = None
            if scene == TABLE_SCENE:
                ref, tgt, tables = simulate_table_scene(workdir)
            elif scene == PHASEREF_SCENE:
                pairs, tables = simulate_phaseref_scene(workdir), None
            else:
                (ref, tgt), tables = simulate(scene, workdir), None
            for name, kwargs in selected:
                if pairs is not None:
                    kwargs = dict(kwargs)
                    ref, tgt = pairs[kwargs.pop("pair")]
                digests, report, elapsed = run_case(ref, tgt, kwargs, workdir, scheduler, tables)
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
    parser.add_argument("--scenes", default=",".join(SCENES),
                        help="comma-separated, of "
                        f"{', '.join(SCENES + (TABLE_SCENE, PHASEREF_SCENE))}")
    parser.add_argument("--only", help="run only the cases whose scene/name contains this")
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
    # the cases this check ran: of the scenes asked for, and matching --only
    scenes = args.scenes.split(",")
    before = {k: v for k, v in before.items() if k.split("/")[0] in scenes
              and (not args.only or args.only in k)}
    lines = differences(before, now)
    for line in lines:
        print(line)
    print(f"{len(now)} cases compared: {'no differences' if not lines else f'{len(lines)} differences'}")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
