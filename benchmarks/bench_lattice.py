"""How often does the antenna lattice solve of the n0 offsets pick the true point?  (issue 16)

End to end: ``hitops calibrate --tracker antenna --offset-model MODEL_DATA`` on synthetic
pairs (hitops.testing.make_pair) of N stations whose tracks are cut into
10-minute scans (1 s samples, RR and LL; every scan restarts the counts, so every scan
and hand needs its own integers), thermal noise at both bands at per-sample SNR rho
(amplitude / noise per component, as in docs/tracking.md), troposphere a random walk of
0.05 rad per sample at 86 GHz.  The model column holds the true source phase.

The truth is exact whatever the noise: the antenna tracker's baseline model (R times it
is what the target receives) is captured from the run, and its count error against the
true reference phase, d = round((model - true) / 2 pi), is what the output carries
(-2 pi eps d).  A segment (scan x hand) is *right* when the step's integer equals d
modulo the lattice period on every baseline, *wrong* when not, and *slip* when d
changes inside it (a tracking failure, not the solve's; left out of the rate).

The step's inputs (the edge sums and the tracker's antenna phases) are captured from the
run and solved again offline two ways: **per hand** (each hand alone: the solve before
this benchmark) and **both hands** (the hands tied per antenna through the reference
band, the default now).  For every wrong segment of the per-hand solve the score
sum_e Re(z_e exp(-i 2 pi eps d_e)) of the truth is compared with the chosen point's: a
truth that scores higher is a *search* failure (the optimiser missed the maximum), a
truth that scores lower an *information* failure (the data prefer the wrong point: no
search can fix it).  The measured per-antenna offset error (rms of the chosen nodes'
residuals in right segments) is compared with the prediction
sigma_b / sqrt((N - 1) T) per antenna and hand, sigma_b^2 = s_t^2 + R^2 s_r^2 the
per-sample variance of the calibrated phase on one baseline (s the rms phase of a noisy
unit phasor at SNR rho, Monte Carlo), T the samples of the segment.

Writes the table into docs/calibrate.md (section ``lattice-solve-rate``) and the figure
docs/figures/lattice_solve_rate.png.

Run: ``python -m benchmarks.bench_lattice [--scans N] [--stations 4,6,8] [--rho 3,2.5,2,1.75,1.5]``.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ._report import ROOT, machine_line, replace_section

DOC = ROOT / "docs" / "calibrate.md"
FIGURE = ROOT / "docs" / "figures" / "lattice_solve_rate.png"
EPS = 230.0 / 86.0 - 2
PERIOD = 43


def phase_rms(rho: float, n: int = 400_000, seed: int = 1) -> float:
    """rms phase (rad) of 1 + complex Gaussian noise of std 1/rho per component."""
    rng = np.random.default_rng(seed)
    z = 1 + (rng.normal(0, 1 / rho, n) + 1j * rng.normal(0, 1 / rho, n))
    return float(np.sqrt(np.mean(np.angle(z) ** 2)))


def classify(rep_series, d_truth, z_of, flagged):
    """Per (scan, corr): right / wrong / slip, plus the search-or-information verdict."""
    out = {}
    for key, per_bl in d_truth.items():
        if per_bl is None:
            out[key] = ("slip", None)
            continue
        ok = True
        s_truth = s_found = 0.0
        for bl, d in per_bl.items():
            k = rep_series.get(key + (bl,))
            if k is None or (k - d) % PERIOD:
                ok = False
            z = z_of.get(key + (bl,))
            if z is not None and k is not None:
                s_truth += (z * np.exp(-2j * np.pi * EPS * d)).real
                s_found += (z * np.exp(-2j * np.pi * EPS * k)).real
        if ok:
            out[key] = ("right", None)
        else:
            out[key] = ("wrong", ("search" if s_truth > s_found + 1e-9 * abs(s_found)
                                  else "information", key in flagged))
    return out


def run_cell(workdir: Path, n_ant: int, rho: float, n_scans: int, seed: int) -> dict:
    from hitops.calibrate import calibrate_flat
    from hitops.calibrate import offset_step as offsets

    from .bench_offsets import antenna_scene, capture_antenna_model

    truth = antenna_scene(workdir, n_ant, rho, n_scans, seed)
    captured = {}
    original_solve = offsets.antenna_offsets

    def solve(*args, **kwargs):
        captured.update(args=args, kwargs=dict(kwargs))
        t0 = time.perf_counter()
        result = original_solve(*args, **kwargs)
        captured["solve_s"] = time.perf_counter() - t0
        return result

    offsets.antenna_offsets = solve
    try:
        with capture_antenna_model(captured):
            t0 = time.perf_counter()
            rep = calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna",
                            offset_model="MODEL_DATA", overwrite=True, no_verdict=True)
            wall = time.perf_counter() - t0
    finally:
        offsets.antenna_offsets = original_solve
    if rep["chunks"] != 1:
        raise RuntimeError("one chunk expected")
    names = [s["antenna"] for s in rep["tracking"]["antennas"]]
    model = captured["model"]
    t_idx = np.searchsorted(captured["times"], truth.time)
    # the truth per (scan, corr): {baseline name: d}, None for a slip
    d_truth = {}
    scans = np.unique(truth.scan)
    for s in scans:
        for c, corr in enumerate(("RR", "LL")):
            per_bl = {}
            for b, (p, q) in enumerate(zip(captured["ant1"], captured["ant2"])):
                rows = np.flatnonzero((truth.ant1 == p) & (truth.ant2 == q) & (truth.scan == s))
                m = model[b, c, t_idx[rows]]
                ok = np.isfinite(m)
                if ok.sum() < 10:
                    continue
                d = np.rint((m[ok] - truth.ref_phase_true[rows[ok], c]) / (2 * np.pi)).astype(int)
                if np.unique(d).size > 1:
                    per_bl = None
                    break
                per_bl[f"{names[p]}-{names[q]}"] = int(d[0])
            d_truth[(int(s), corr)] = per_bl
    args, kwargs = captured["args"], captured["kwargs"]
    seg_sums, _, _, _, _, baseline_names, corr_names, scan_numbers = args[:8]
    z_of = {}
    for (b, c, key), (z, n) in seg_sums.items():
        k = (int(scan_numbers[key // kwargs["segment_key"]]), corr_names[c], baseline_names[b])
        z_of[k] = z_of.get(k, 0) + complex(z)
    result = {"n_ant": n_ant, "rho": rho, "wall": wall}
    for variant, hands in (("per hand", None), ("both hands", kwargs.get("hands"))):
        t0 = time.perf_counter()
        _, antennas, _, series = original_solve(*args, **{**kwargs, "hands": hands})
        solve_s = time.perf_counter() - t0
        found = {(e["scan"], e["correlation"], e["baseline"]): e["k"] for e in series}
        flagged = {(e["scan"], e["correlation"]) for e in antennas if e.get("ambiguous")}
        cls = classify(found, d_truth, z_of, flagged)
        right = sum(v[0] == "right" for v in cls.values())
        wrong = [v[1] for v in cls.values() if v[0] == "wrong"]
        slips = sum(v[0] == "slip" for v in cls.values())
        right_keys = {k for k, v in cls.items() if v[0] == "right"}
        res = [e["residual_deg"] for e in antennas
               if (e["scan"], e["correlation"]) in right_keys and not e["reference"]
               and e.get("residual_deg") is not None]
        result[variant] = {
            "right": right, "wrong": len(wrong), "slips": slips,
            "rate": 100.0 * right / max(1, right + len(wrong)),
            "search": sum(w[0] == "search" for w in wrong),
            "information": sum(w[0] == "information" for w in wrong),
            "flagged": sum(bool(w[1]) for w in wrong),
            "ambiguous": sum(bool(e.get("ambiguous")) for e in antennas),
            "node_rms_deg": float(np.sqrt(np.mean(np.square(res)))) if res else float("nan"),
            "solve_s": solve_s}
    s_b = math.sqrt(phase_rms(rho) ** 2 + (230 / 86) ** 2 * phase_rms(rho) ** 2)
    result["predicted_node_deg"] = math.degrees(s_b / math.sqrt((n_ant - 1) * 600))
    shutil.rmtree(workdir, ignore_errors=True)
    return result


def whole_track_coherence(workdir: Path, seed: int = 42) -> dict:
    """The paper scene, with and without thermal noise (same troposphere): whole-track
    coherence of the no-control PWC column per baseline and hand, and what the noise alone
    leaves.

    ``hitops simulate paper`` twice with the same seed (``--no-noise`` for the second:
    the same troposphere, no thermal noise), then ``hitops calibrate --tracker antenna
    --offset-model point`` on each.  Coherence: |mean over the unflagged samples of the
    whole track of exp(i phase)| of the output (a point source at the phase centre: phase
    0 is the truth).  ``ratio``: the same for output_noisy * conj(output_noise_free),
    i.e. the per-sample thermal noise that reaches the output (target noise plus R times
    the reference band's noise through the antenna solutions) when the integers agree.
    """
    import subprocess
    from casacore import tables as pt

    hitops = str(Path(sys.executable).parent / "hitops")
    out = {}
    for label, extra in (("noisy", []), ("noise-free", ["--no-noise"])):
        d = workdir / label
        subprocess.run([hitops, "simulate", "paper", "--outdir", str(d), "--seed", str(seed),
                        "--overwrite", *extra], check=True, capture_output=True)
        t0 = time.perf_counter()
        subprocess.run([hitops, "calibrate", str(d / "sim-86.ms"), str(d / "sim-230.ms"),
                        "--method", "pwc", "--tracker", "antenna", "--offset-model", "point",
                        "--output-column", "PWC_NC_DATA", "--no-verdict", "--overwrite"],
                       check=True, capture_output=True)
        with pt.table(str(d / "sim-230.ms"), ack=False) as t:
            out[label] = dict(vis=t.getcol("PWC_NC_DATA")[:, 0, :], flag=t.getcol("FLAG")[:, 0, :],
                              a1=t.getcol("ANTENNA1"), a2=t.getcol("ANTENNA2"),
                              time=t.getcol("TIME"), corr=["RR", "LL"])
            names = pt.table(str(d / "sim-230.ms") + "/ANTENNA", ack=False).getcol("NAME")
        out[label]["wall"] = time.perf_counter() - t0
    a, b = out["noisy"], out["noise-free"]
    if not (np.array_equal(a["a1"], b["a1"]) and np.array_equal(a["time"], b["time"])):
        raise RuntimeError("the two simulations lay their rows out differently")
    rows = []
    for p, q in sorted(set(zip(a["a1"].tolist(), a["a2"].tolist()))):
        sel = (a["a1"] == p) & (a["a2"] == q)
        for c, corr in enumerate(("RR", "LL")):
            ok = sel & ~a["flag"][:, c] & ~b["flag"][:, c]
            if ok.sum() < 100:
                continue
            u_noisy = a["vis"][ok, c] / np.abs(a["vis"][ok, c])
            u_free = b["vis"][ok, c] / np.abs(b["vis"][ok, c])
            ratio = u_noisy * np.conj(u_free)
            # 60-s coherence: mean over 60-s blocks of |mean exp(i phase)|
            tt = a["time"][ok] - a["time"][ok].min()
            blocks = (tt // 60).astype(int)
            c60 = np.mean(np.abs(np.bincount(blocks, u_noisy.real) + 1j * np.bincount(blocks, u_noisy.imag))
                          / np.maximum(np.bincount(blocks), 1))
            rows.append({"baseline": f"{names[p]}-{names[q]}", "corr": corr,
                         "noisy": float(abs(u_noisy.mean())), "noise_free": float(abs(u_free.mean())),
                         "ratio": float(abs(ratio.mean())), "noisy_60s": float(c60),
                         # the Gaussian small-noise form of the same: exp(-var/2)
                         "phase_rms_deg": float(np.degrees(np.sqrt(np.mean(np.angle(ratio) ** 2))))})
    return {"rows": rows, "wall": {k: out[k]["wall"] for k in out}}


def speed(workdir: Path, repeats: int) -> str:
    """What the step adds to calibrate on benchmarks/bench_calibrate.py's paper-size pair,
    with one chunk and with ``--chunk-rows 200000``: ``--tracker antenna`` with no step and
    with ``--offset-model point``, whole processes, interleaved, warm numba cache."""
    import json
    import os

    from ._report import median, run_process
    from .bench_calibrate import build

    ref_ms, target_ms = build(workdir)
    hitops = str(Path(sys.executable).with_name("hitops"))
    base = [hitops, "calibrate", str(ref_ms), str(target_ms), "--method", "pwc", "--tracker",
            "antenna", "--overwrite", "--no-verdict"]
    lines = []
    for chunking in ([], ["--chunk-rows", "200000"]):
        commands = {"none": base + chunking + ["--report", str(workdir / "r-none.json")],
                    "point": base + chunking + ["--report", str(workdir / "r-point.json"),
                                                "--offset-model", "point"]}
        for command in commands.values():
            run_process(command)
        runs = {k: [] for k in commands}
        load = os.getloadavg()[0]
        for _ in range(repeats):
            for key, command in commands.items():
                runs[key].append(run_process(command)["wall_s"])
        rep = json.loads((workdir / "r-point.json").read_text())
        ratio = median([p / n for p, n in zip(runs["point"], runs["none"])])
        lines.append(
            f"| {'one chunk' if not chunking else '--chunk-rows 200000'} | {rep['chunks']} | "
            f"{median(runs['none']):.2f} | {median(runs['point']):.2f} | {100 * (ratio - 1):.1f} | "
            f"{rep['timings_s'].get('offset_solve', float('nan')):.3f} | {load:.1f} |")
        print(lines[-1], flush=True)
    return ("| chunks | time chunks | no step, median wall (s) | `--offset-model point`, median "
            "wall (s) | added (%, median of run-by-run ratios) | lattice solves (s) | load "
            "average |\n|---|---|---|---|---|---|---|\n" + "\n".join(lines))


def figure(rows, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.2))
    colours = {4: "tab:red", 6: "tab:blue", 8: "tab:green", 5: "tab:orange", 3: "tab:purple"}
    for n_ant in sorted({r["n_ant"] for r in rows}):
        sel = sorted((r for r in rows if r["n_ant"] == n_ant), key=lambda r: r["rho"])
        rho = [r["rho"] for r in sel]
        for variant, style in (("per hand", "--"), ("both hands", "-")):
            ax.plot(rho, [r[variant]["rate"] for r in sel], style, marker="o",
                    color=colours.get(n_ant, "k"),
                    label=f"{n_ant} stations, {variant}")
    ax.axhline(99, color="0.3", lw=0.9, ls=":")
    ax.text(max(r["rho"] for r in rows), 97.6, "99 % (target) ", color="0.3", fontsize=8,
            ha="right", va="top")
    ax.set_xlabel("per-sample SNR rho (both bands, per baseline)")
    ax.set_ylabel("segments solved right (%, slipped ones left out)")
    ax.set_title("Antenna lattice solve of n0, 10-min segments, eps = 29/43")
    ax.set_ylim(min(60, min(min(r[v]["rate"] for v in ("per hand", "both hands"))
                            for r in rows) - 2), 100.5)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=100, help="10-minute scans per run")
    parser.add_argument("--stations", default="4,6,8")
    parser.add_argument("--rho", default="3,2.5,2,1.75,1.5")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--speed", action="store_true",
                        help="only what the step adds to calibrate on the paper-size pair, "
                        "one chunk and --chunk-rows 200000 (printed)")
    parser.add_argument("--repeats", type=int, default=5, help="--speed: interleaved runs")
    parser.add_argument("--coherence", action="store_true",
                        help="only the whole-track coherence of the paper scene with and "
                        "without thermal noise (printed)")
    parser.add_argument("--from-log", help="rebuild the table and figure from the result "
                        "lines (one dict per cell) a run printed, with its wall time in s "
                        "as LOG:SECONDS")
    args = parser.parse_args(argv if argv is not None else [])
    stations = [int(x) for x in args.stations.split(",")]
    rhos = [float(x) for x in args.rho.split(",")]
    rows = []
    started = time.perf_counter()
    if args.speed:
        workdir = Path(tempfile.mkdtemp(prefix="bench-lattice-speed-"))
        try:
            print(speed(workdir, args.repeats))
        finally:
            shutil.rmtree(workdir, ignore_errors=True)
        return
    if args.coherence:
        workdir = Path(tempfile.mkdtemp(prefix="bench-lattice-coh-"))
        try:
            res = whole_track_coherence(workdir)
        finally:
            shutil.rmtree(workdir, ignore_errors=True)
        print("| baseline | hand | whole track, noisy | whole track, noise-free | noisy / noise-free "
              "| noisy, 60 s | rms phase of noisy / noise-free (deg) |")
        print("|---|---|---|---|---|---|---|")
        for r in sorted(res["rows"], key=lambda r: r["noisy"]):
            print(f"| {r['baseline']} | {r['corr']} | {r['noisy']:.4f} | {r['noise_free']:.5f} | "
                  f"{r['ratio']:.4f} | {r['noisy_60s']:.4f} | {r['phase_rms_deg']:.1f} |")
        print(res["wall"], f"total {time.perf_counter() - started:.0f} s")
        return
    if args.from_log:
        import ast
        log_path, seconds = args.from_log.rsplit(":", 1)
        rows = [ast.literal_eval(line) for line in Path(log_path).read_text().splitlines()
                if line.startswith("{'n_ant'")]
        stations = sorted({r["n_ant"] for r in rows})
        total = float(seconds)
    else:
        for n_ant in stations:
            for i, rho in enumerate(rhos):
                workdir = Path(tempfile.mkdtemp(prefix="bench-lattice-"))
                r = run_cell(workdir, n_ant, rho, args.scans, seed=700 + 10 * n_ant + i)
                print(r, flush=True)
                rows.append(r)
        total = time.perf_counter() - started

    def cells(v, diagnose=True):
        return (f"{v['right']} | {v['wrong']} | {v['rate']:.1f} | "
                + (f"{v['search']} / {v['information']} | " if diagnose else "")
                + f"{v['flagged']} of {v['wrong']} | {v['node_rms_deg']:.2f}")

    table = "\n".join(
        f"| {r['n_ant']} | {r['rho']:.2f} | {r['per hand']['slips']} | {cells(r['per hand'])} | "
        f"{cells(r['both hands'], False)} | {r['predicted_node_deg']:.2f} |" for r in rows)
    limit = []
    for n_ant in stations:
        sel = sorted((r for r in rows if r["n_ant"] == n_ant), key=lambda r: -r["rho"])
        for variant in ("per hand", "both hands"):
            ok = [r["rho"] for r in sel if r[variant]["rate"] >= 99.0]
            # the lowest SNR from which every higher swept SNR is >= 99 %
            low = None
            for r in sel:
                if r[variant]["rate"] >= 99.0:
                    low = r["rho"]
                else:
                    break
            limit.append(f"{n_ant} stations, {variant}: >= 99 % down to rho = "
                         + (f"{low:g}" if low is not None else "none swept")
                         + ("" if len(ok) == len(sel) else
                            f" (below 99 % at rho = {', '.join(f'{r:g}' for r in sel_rhos(sel, variant))})"))
    markdown = f"""Machine: {machine_line()}.  `python -m benchmarks.bench_lattice --scans {args.scans}` ({total:.0f} s).

`hitops calibrate --tracker antenna --offset-model MODEL_DATA` (model = the true source
phase) on make_pair scenes: {args.scans} scans of 10 min (600 samples of 1 s) per run, RR
and LL, thermal noise at both bands at per-sample SNR rho, troposphere a random walk of
0.05 rad per sample at 86 GHz; segments = scans x hands ({2 * args.scans} per cell).
*Right*: the integer equals the tracker's count error (modulo 43) on every baseline of
the segment; *slip*: the count error changes inside the segment (the tracker's failure,
left out); rate = right / (right + wrong).  *search / information* (per hand, the
solve this table was made to diagnose): of the wrong segments, those whose true
integers score higher than the chosen ones (the optimiser missed the maximum) and those
whose true integers score lower (the data prefer the wrong point).  *Flagged*: wrong segments with an antenna marked `ambiguous`.  Node
error: rms residual (deg) of the chosen antenna segments in right segments (half the
lattice spacing is 4.19 deg); predicted: sigma_b / sqrt((N-1) T) for one hand.

| stations | rho | slip | per hand: right | wrong | rate (%) | search / information | flagged | node error (deg) | both hands: right | wrong | rate (%) | flagged | node error (deg) | predicted node error, one hand (deg) |
|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|
{table}

{'; '.join(limit)}.

![solve rate](figures/lattice_solve_rate.png)"""
    print(markdown)
    if not args.no_write:
        figure(rows, FIGURE)
        replace_section("lattice-solve-rate", markdown, DOC)


def sel_rhos(sel, variant):
    return [r["rho"] for r in sel if r[variant]["rate"] < 99.0]


if __name__ == "__main__":
    main(sys.argv[1:])
