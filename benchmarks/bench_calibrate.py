"""Benchmark of what a user runs: ``hitops calibrate`` with default options (issue 28).

Two paper-size pairs (8 stations, 28 baselines, 12 h of 1 s: 1 209 600 rows per band):

* ``paper``: ``hitops simulate paper`` (RR/LL, troposphere and noise), as a user
  makes it;
* ``casa``: the same stations and times laid out by casatools.simulator
  (benchmarks/casa_layout.py) with four correlations (RR, RL, LR, LL), DATA then
  filled with a random-walk troposphere (R times larger at 230 GHz), thermal noise
  and small cross hands (:func:`fill_casa_pair`), since the simulator leaves it
  without signal.

Each figure is a whole process (benchmarks/_report.run_process), warm numba cache:
``hitops calibrate REF TGT --overwrite`` (default options: PWC, the verdict) and the
same with ``--no-verdict``, interleaved with the same-stack floor
(benchmarks/_floors.py: importing the stack and starting numba's CPU target, then
reading every column calibrate reads and writing one column) so a change of the
machine's load hits all three alike; ratios are taken run by run, and the
1-minute load average is recorded before each triple.  The machine is shared by
several agents: the load column says how much.

Run: ``python -m benchmarks.bench_calibrate [--workdir DIR] [--repeats N]
[--scenes paper,casa]`` (writes the ``calibrate`` section of docs/performance.md);
``--offset-step`` measures what ``--offset-model point`` adds (docs/calibrate.md),
``--figure`` redraws the CFPT/PWC figure.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ._floors import LABELS as FLOOR_LABELS, floor_commands
from ._report import PLOT_DIR, machine_line, median, replace_section, run_process, save_figure

N_TIME = 43_200
N_ANT = 8
CORRS = ("RR", "RL", "LR", "LL")

def build(workdir: Path, time_order: bool = False):
    """The paper-size pair in ``workdir`` (baseline by baseline, or sorted by time)."""
    from hitops.testing import PairSpec, Signal, Storage, Troposphere, make_pair

    if (workdir / "target.ms" / "table.dat").exists() and (workdir / "ref.ms" / "table.dat").exists():
        return workdir / "ref.ms", workdir / "target.ms"
    t0 = time.perf_counter()
    spec = PairSpec(n_ant=N_ANT, n_time=N_TIME, corr_types=CORRS, seed=2023,
                    troposphere=Troposphere(step_rad=0.05, drift_rad=0.01),
                    signal=Signal(sigma_ref=0.05, sigma_target=0.1),
                    storage=Storage(time_order=time_order))
    truth = make_pair(workdir, spec)
    print(f"built the pair in {time.perf_counter() - t0:.1f} s", flush=True)
    return truth.ref_ms, truth.target_ms


def figure(path: Path) -> Path:
    """CFPT and PWC residuals of one synthetic baseline with the reference wraps marked.

    The analogue of the paper's Fig. (cfpt_vs_pwc_phase_w_wrap_positions), made by
    running the tool itself on a small pair with a known source phase.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from casacore import tables as pt

    from hitops.calibrate import calibrate_flat
    from hitops.testing import PairSpec, Signal, Troposphere, make_pair, wrap
    from hitops.tracking.count import count_wraps

    workdir = Path(tempfile.mkdtemp(prefix="fig-calibrate-"))
    truth = make_pair(workdir, PairSpec(
        n_ant=3, n_time=1800, seed=5,
        troposphere=Troposphere(step_rad=0.04, drift_rad=0.03, phase_offset_rad=1.0),
        signal=Signal(sigma_ref=0.03, sigma_target=0.08)))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    with pt.table(str(truth.target_ms), ack=False) as t:
        cfpt = np.angle(t.getcol("CFPT_DATA")[:, 0, 0])
        pwc = np.angle(t.getcol("PWC_DATA")[:, 0, 0])
    with pt.table(str(truth.ref_ms), ack=False) as t:
        ref = np.angle(t.getcol("DATA")[:, 0, 0]).astype(np.float64)
    sel = (truth.ant1 == 0) & (truth.ant2 == 1)
    order = np.argsort(truth.time[sel])
    minutes = (truth.time[sel][order] - truth.time.min()) / 60.0
    source = truth.source_phase[sel][order, 0]
    n = count_wraps(ref[sel][order], np.ones(order.size, bool))
    fig, ax = plt.subplots(figsize=(8, 3.4))
    for t_wrap in minutes[1:][np.diff(n) != 0]:
        ax.axvline(t_wrap, color="0.8", lw=0.6, ls="--", zorder=0)
    ax.plot(minutes, np.degrees(wrap(cfpt[sel][order] - source)), ".", ms=1.5, label="CFPT")
    ax.plot(minutes, np.degrees(wrap(pwc[sel][order] - source)), ".", ms=1.5, label="PWC")
    ax.set_xlabel("time (min)")
    ax.set_ylabel("residual phase at 230 GHz (deg)")
    ax.set_ylim(-185, 185)
    ax.set_title("R = 230/86: CFPT jumps by -117.2 deg at every 86 GHz wrap (dashed); PWC does not",
                 fontsize=9)
    ax.legend(markerscale=6, loc="lower left", fontsize=8)
    save_figure(fig, path)
    shutil.rmtree(workdir, ignore_errors=True)
    return path


def measure_offset_step(workdir: Path, ref_ms: Path, target_ms: Path, repeats: int) -> str:
    """What the n0 step against a model adds (issue 16): ``--tracker antenna`` without a step
    and with ``--offset-model point``, whole processes interleaved, on the paper-size pair.

    Returns the markdown written between ``<!-- bench:calibrate-offset-step -->`` markers
    of docs/calibrate.md.
    """
    from ._report import ROOT

    from hitops.schema import load_schema

    hitops = str(Path(sys.executable).with_name("hitops"))
    # without the verdict where calibrate has one (it reads both bands whole, the same in
    # both runs, and would hide the step's share)
    quiet = ["--no-verdict"] if "no_verdict" in load_schema("calibrate")["inputs"] else []
    base = [hitops, "calibrate", str(ref_ms), str(target_ms), "--method", "pwc", "--tracker",
            "antenna", "--overwrite"] + quiet + ["--report"]
    commands = {"none": base + [str(workdir / "report-nostep.json")],
                "point": base + [str(workdir / "report-point.json"), "--offset-model", "point"]}
    for command in commands.values():   # numba caches warm, the column exists
        run_process(command)
    runs = {k: [] for k in commands}
    load_before = os.getloadavg()[0]
    for _ in range(repeats):
        for key, command in commands.items():
            runs[key].append(run_process(command)["wall_s"])
    load_after = os.getloadavg()[0]
    reports = {k: json.loads((workdir / f"report-{'nostep' if k == 'none' else 'point'}.json")
                             .read_text()) for k in commands}
    wall = {k: median(v) for k, v in runs.items()}
    pairwise = median([p / n for p, n in zip(runs["point"], runs["none"])])
    inside = {k: reports[k]["time_s"] for k in reports}
    stage = reports["point"]["timings_s"]
    markdown = f"""Machine: {machine_line()}; load average {load_before:.1f} before, {load_after:.1f}
after.  Pair: benchmarks/bench_calibrate.py's paper-size scene ({N_ANT} stations, {N_TIME} times
of 1 s, {len(CORRS)} correlations, {28 * N_TIME} rows per band, one chunk), `hitops calibrate
--method pwc --tracker antenna{" --no-verdict" if quiet else ""}`, whole processes, warm numba
cache, the two runs interleaved {repeats} times.

| run | wall, median (s) | runs (s) | inside `calibrate_flat()`, last run (s) |
|---|---|---|---|
| no offset step | {wall["none"]:.2f} | {", ".join(f"{x:.2f}" for x in runs["none"])} | {inside["none"]:.2f} |
| `--offset-model point` | {wall["point"]:.2f} | {", ".join(f"{x:.2f}" for x in runs["point"])} | {inside["point"]:.2f} |

The step adds {100 * (pairwise - 1):.1f} % (median of the run-by-run ratios; target <= 20 %:
{"met" if pairwise <= 1.2 else "NOT met"}).  Its own stages in the last run: the lattice solves
and the per-baseline choices (cross hands) {stage.get("offset_solve", float("nan")):.3f} s, the
shift of the kept output {stage.get("offset_apply", float("nan")):.3f} s; the rest is the sums of
output against model per baseline segment (one numba pass over the rows) and the larger
report.  With the smooth and antenna trackers the first pass's output is kept (when it
fits in a fifth of `--memory-budget`, one chunk or several) and shifted by 2 pi eps k
per segment: no second tracking or transfer; the count tracker's per-baseline step
runs the transfer again.

Run: `python -m benchmarks.bench_calibrate --offset-step [--workdir DIR] [--repeats N]`."""
    replace_section("calibrate-offset-step", markdown, ROOT / "docs" / "calibrate.md")
    return markdown


def build_paper(workdir: Path):
    """``hitops simulate paper`` into ``workdir/paper`` (reused when present)."""
    out = workdir / "paper"
    ref, tgt = out / "sim-86.ms", out / "sim-230.ms"
    if not (tgt / "table.dat").exists():
        hitops = str(Path(sys.executable).with_name("hitops"))
        run_process([hitops, "simulate", "paper", "--outdir", str(out), "--overwrite"])
    return ref, tgt


def fill_casa_pair(ref_ms: Path, target_ms: Path, ratio: float = 230.0 / 86.0,
                   seed: int = 28) -> None:
    """DATA of a casatools.simulator layout: per-antenna random-walk phases (0.05 rad per
    sample at the reference band, R times that at the target band), unit parallel hands,
    cross hands of 0.02, thermal noise of 0.05 (reference) and 0.1 (target) per part."""
    import numpy as np
    from casacore import tables as pt

    rng = np.random.default_rng(seed)
    with pt.table(str(ref_ms), ack=False) as t:
        time, ant1, ant2 = t.getcol("TIME"), t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        n_ant = int(max(ant1.max(), ant2.max())) + 1
    times, t_idx = np.unique(time, return_inverse=True)
    walk = np.cumsum(rng.normal(0.0, 0.05, (times.size, n_ant)), axis=0)
    phase = walk[t_idx, ant1] - walk[t_idx, ant2]
    for ms, scale, sigma in ((ref_ms, 1.0, 0.05), (target_ms, ratio, 0.1)):
        with pt.table(str(ms), readonly=False, ack=False) as t:
            if not np.array_equal(t.getcol("TIME"), time):
                raise RuntimeError(f"{ms}: not the same layout as {ref_ms}")
            n_row = time.size
            vis = np.empty((n_row, 1, 4), dtype=np.complex64)
            signal = np.exp(1j * scale * phase)
            amp = np.array([1.0, 0.02, 0.02, 1.0])
            for c in range(4):
                noise = rng.normal(0, sigma, n_row) + 1j * rng.normal(0, sigma, n_row)
                vis[:, 0, c] = amp[c] * signal + noise
            t.putcol("DATA", vis)
            t.putcol("FLAG", np.zeros((n_row, 1, 4), dtype=bool))


def build_casa(workdir: Path):
    """The casatools.simulator layout of the paper scene, four correlations, both bands."""
    out = workdir / "casa"
    ref, tgt = out / "casa-86.ms", out / "casa-230.ms"
    if not (out / "filled").exists():
        out.mkdir(parents=True, exist_ok=True)
        layout = str(Path(__file__).with_name("casa_layout.py"))
        for band, ms in (("86", ref), ("230", tgt)):
            if not (ms / "table.dat").exists():
                run_process([sys.executable, layout, "paper", str(ms), "--band", band,
                             "--correlations", "RR,RL,LR,LL"])
        fill_casa_pair(ref, tgt)
        (out / "filled").write_text("DATA filled by benchmarks/bench_calibrate.fill_casa_pair\n")
    return ref, tgt


def measure_scene(workdir: Path, tag: str, ref_ms: Path, target_ms: Path, repeats: int) -> dict:
    """Floor, default run and --no-verdict run, interleaved ``repeats`` times."""
    hitops = str(Path(sys.executable).with_name("hitops"))
    commands = {"default": [hitops, "calibrate", str(ref_ms), str(target_ms), "--overwrite",
                            "--report", str(workdir / f"report-{tag}-default.json")],
                "no_verdict": [hitops, "calibrate", str(ref_ms), str(target_ms), "--overwrite",
                               "--no-verdict", "--report",
                               str(workdir / f"report-{tag}-no-verdict.json")]}
    floor_cmd = floor_commands(workdir, ref_ms, target_ms)["same_stack"]
    run_process(commands["default"])   # the column exists, numba's cache is warm
    run_process(floor_cmd)
    rows = []
    for _ in range(repeats):
        load = os.getloadavg()[0]
        floor = run_process(floor_cmd)
        default = run_process(commands["default"])
        quiet = run_process(commands["no_verdict"])
        report = json.loads((workdir / f"report-{tag}-default.json").read_text())
        rows.append({"load": load, "floor": floor, "default": default, "no_verdict": quiet,
                     "timings": report.get("timings_s", {}), "time_s": report.get("time_s"),
                     "verdict_output": "warn" if "WARNING" in default["output"] and
                     "closure" in default["output"] else "",
                     "stray_lines": sum(1 for line in default["output"].splitlines()
                                        if line and not line[:2].isdigit())})
    return {"rows": rows, "commands": commands}


def scene_markdown(title: str, result: dict) -> str:
    rows = result["rows"]
    ratio = {k: median([r[k]["wall_s"] / r["floor"]["wall_s"] for r in rows])
             for k in ("default", "no_verdict")}
    cpu_ratio = {k: median([r[k]["cpu_s"] / r["floor"]["cpu_s"] for r in rows])
                 for k in ("default", "no_verdict")}
    verdict = [r["timings"].get("verdict", float("nan")) for r in rows]
    share = median([r["timings"].get("verdict", 0.0) / r["default"]["wall_s"] for r in rows])
    peak = max(r["default"]["peak_rss_mb"] for r in rows)
    lines = [f"**{title}**: default options {median([r['default']['wall_s'] for r in rows]):.2f} s"
             f" wall median ({ratio['default']:.2f}x the same-stack floor run by run; CPU "
             f"{cpu_ratio['default']:.2f}x), `--no-verdict` "
             f"{median([r['no_verdict']['wall_s'] for r in rows]):.2f} s ({ratio['no_verdict']:.2f}x; "
             f"CPU {cpu_ratio['no_verdict']:.2f}x), floor "
             f"{median([r['floor']['wall_s'] for r in rows]):.2f} s; the verdict "
             f"{median(verdict):.2f} s inside the run ({100 * share:.0f}% of the default "
             f"run's wall time); peak RSS {peak:.0f} MB; lines on stderr that are not log "
             f"lines: {max(r['stray_lines'] for r in rows)}.",
             "",
             "| run | load (1 min) | floor wall / CPU (s) | default wall / CPU (s) | "
             "`--no-verdict` wall / CPU (s) | default / floor | stages of the default run (s) |",
             "|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows, 1):
        stages = ", ".join(f"{k} {v:.2f}" for k, v in r["timings"].items())
        lines.append(f"| {i} | {r['load']:.1f} | {r['floor']['wall_s']:.2f} / "
                     f"{r['floor']['cpu_s']:.2f} | {r['default']['wall_s']:.2f} / "
                     f"{r['default']['cpu_s']:.2f} | {r['no_verdict']['wall_s']:.2f} / "
                     f"{r['no_verdict']['cpu_s']:.2f} | "
                     f"{r['default']['wall_s'] / r['floor']['wall_s']:.2f} | {stages} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None, help="where to build (and reuse) the pairs")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--scenes", default="paper,casa")
    parser.add_argument("--offset-step", action="store_true",
                        help="only measure what --offset-model point adds (docs/calibrate.md)")
    parser.add_argument("--figure", action="store_true",
                        help="only redraw docs/figures/calibrate_cfpt_vs_pwc.png")
    args = parser.parse_args(argv if argv is not None else [])
    if args.figure:
        print("figure:", figure(PLOT_DIR / "calibrate_cfpt_vs_pwc.png"))
        return
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-calibrate-"))
    workdir.mkdir(parents=True, exist_ok=True)
    if args.offset_step:
        ref_ms, target_ms = build(workdir)
        print(measure_offset_step(workdir, ref_ms, target_ms, args.repeats))
        if not args.workdir:
            shutil.rmtree(workdir, ignore_errors=True)
        return
    builders = {"paper": (build_paper, "`hitops simulate paper` (RR, LL; rows in time order)"),
                "casa": (build_casa, "casatools.simulator layout, four correlations "
                                     "(RR, RL, LR, LL; rows in time order)")}
    load_before = os.getloadavg()
    for tag in args.scenes.split(","):
        build_scene, title = builders[tag]
        ref_ms, target_ms = build_scene(workdir)
        result = measure_scene(workdir, tag, ref_ms, target_ms, args.repeats)
        section = scene_markdown(title, result)
        # kept in the work directory: a later run of the other scene writes both
        (workdir / f"section-{tag}.md").write_text(section)
        print(section, flush=True)
    load_after = os.getloadavg()
    body = "\n\n".join((workdir / f"section-{tag}.md").read_text() for tag in builders
                         if (workdir / f"section-{tag}.md").exists())
    markdown = f"""## hitops calibrate: what a user runs (issue 28)

Machine: {machine_line()}; load average (1, 5, 15 min) {", ".join(f"{x:.1f}" for x in load_before)}
before and {", ".join(f"{x:.1f}" for x in load_after)} after: the machine is shared by several
agents, so wall times carry their load (see the load column, recorded before each
triple of runs); CPU times much less.  Pairs of 8 stations, 12 h of 1 s
(1 209 600 rows per band).  Whole processes, warm numba cache, {args.repeats} interleaved
triples (same-stack floor, `hitops calibrate REF TGT --overwrite`, the same with
`--no-verdict`); ratios are the median of the run-by-run ratios.
{FLOOR_LABELS["same_stack"]} (benchmarks/_floors.py).  Targets (issue 28): default
options <= 1.5x the floor, the verdict <= 10% of the default run, peak <= 1 GB.

{body}

Stages (from each run's report, `timings_s`): `checks` validates the inputs and opens
the subtables; `open` opens the sets for reading (python-casacore directly for a set
of one group on this process, with a time index of the row runs for a set not in time
order cut into chunks, hitops/io/time_sorted.py; dask-ms datasets for several groups
or a cluster); `metadata` is the index pass (TIME, ANTENNA1/2, SCAN_NUMBER, INTERVAL,
FLAG_ROW of both bands; python-casacore getcol), and in a fresh process also numba's import and the
loading of the first cached kernels (the floor pays numba's start too); `match` matches the bands and checks every
cell; `read` reads DATA and FLAG; `transfer` tracks and transfers; `write` writes
the staged output, and the new flags of chunks where they change FLAG (python-casacore
putcol for one-group sets on this process, dask-ms otherwise); `verdict` reads 2 x T/dt-long blocks of times spread over the track
(hitops/calibrate/verdict_sample.py) and predicts.

Run: `python -m benchmarks.bench_calibrate [--workdir DIR] [--repeats N] [--scenes paper,casa]`.
"""
    print(markdown)
    replace_section("calibrate", markdown)
    if not args.workdir:   # pairs built in a temporary directory are not kept
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
