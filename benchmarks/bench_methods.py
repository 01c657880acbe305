"""Error against run time of the calibration methods on the paper's scene (issue 7).

Scene: ``hitops simulate paper --save-truth`` (8 stations, 12 h of 1 s at 86 and
230 GHz, RR/LL, thermal noise and a Kolmogorov troposphere; 350 094 rows per
band above the elevation limits).  Methods, each timed as a whole process
(benchmarks/_report.run_process; median of ``--repeats`` runs for the hitops
methods, one run for CASA):

* CFPT, CWU and PWC with ``hitops calibrate`` (PWC with every wrap tracker
  ``--tracker`` accepts: count, smooth, antenna), each into its own column of
  the 230 GHz set;
* FF+SC: CASA fringefit (solint 20 s) + gaincal (calmode p, 10 s) + applycal,
  through hitops.casa.tasks (the recipe's wrappers, with the recipe's reference
  antenna list, minsnr 3 and minblperant 4), on a separate copy of the 230 GHz
  set so its flags do not touch the other methods' data;
* CWU and PWC (each tracker) again, on the FF+SC copy with the n0 offset step
  against FF+SC's CORRECTED_DATA (``--offset-reference-column CORRECTED_DATA``,
  as recipes/fpt-paper.yml and the paper do): PWC counts wraps from 0 at the
  start of each scan, so without that step every baseline keeps a constant
  2*pi*eps*n0 (antenna-based with ``--tracker antenna``), which an image made
  without self-calibration does not forgive, though the per-baseline phase
  error below does.  Their wall time is calibrate's own; FF+SC must have run
  first.

Accuracy, from the 230 GHz residual phases on the (baseline, time) grid:

* residual phase error against the simulator's truth: the model is a point
  source at the phase centre, so a perfect calibration leaves phase 0 plus
  thermal noise; the error is wrap(arg V) after removing each baseline's
  circular mean (a constant per baseline, such as PWC's 2*pi*eps*n0 or
  FF+SC's reference phase, is absorbed by any later phase calibration), rms over
  all unflagged samples.  The "oracle" row removes the simulator's true
  troposphere (truth .npz, V * exp(-i (phi_p - phi_q))): the thermal floor no
  method can beat;
* coherence factor C(T = 60 s) (mean over baselines of the mean over 60-s
  segments of |<exp(i phi)>|);
* usable fraction: unflagged samples with a calibrated value;
* fractional peak-flux recovery, as the recipe measures it: every column
  (raw DATA, the oracle written to ORACLE_DATA, each method's output) is
  imaged with the real WSClean using the recipe's imaging parameters (read
  from recipes/fpt-paper.yml, recipes/fpt-lib.yml and cabs/wsclean.yml:
  512 x 512 pixels of 2 microarcsec, natural weighting, CLEAN to 10 mJy or
  5000 iterations, mgain 0.5), the peak is fitted with CASA imfit through
  :func:`hitops.casa.imfit` (box of +-32 pixels around the phase centre;
  where CLEAN diverged, |peak| > 5 Jy/beam or no convergence, the dirty
  image's brightest pixel, marked max-pixel) and divided by the scene's
  230 GHz flux by :func:`hitops.compare.compare`.  Imaging time is not
  part of any method's wall time; it is reported per image.

Run: ``python -m benchmarks.bench_methods [--workdir DIR] [--repeats N] [--no-casa]
[--no-imaging]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ._floors import measure_floors
from ._report import (PLOT_DIR, ROOT, machine_line, median, replace_section, run_process,
                      save_figure)

REFANTS = "PV,PB,AP,SM,GL,KP,KC,KY"
SEGMENT_S = 60.0
ORACLE_COLUMN = "ORACLE_DATA"
#: The FPT paper's recoveries (Results; hitops.compare.PAPER) and the recipe run's
#: (docs/paper-rerun.md, recipes/fpt-paper.yml on the same scene), for the text.
PAPER_RECOVERY = {"pwc": 0.965, "ffsc": 0.868}
RECIPE_RECOVERY = {"pwc": 0.994, "ffsc": 0.829, "cfpt": 0.035}

FFSC_SCRIPT = """
import json, sys, time
from pathlib import Path
vis, outdir, refant = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
from hitops.casa_env import ensure_casa_offline
ensure_casa_offline()
timings = {}
try:
    from hitops.casa import tasks
    t0 = time.perf_counter()
    ff = tasks.fringefit(vis, str(outdir / "fringefit.tbl"), solint="20s", refant=refant,
                         minsnr=3.0, overwrite=True)
    timings["fringefit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    gc = tasks.gaincal(vis, str(outdir / "gaincal.tbl"), solint="10s", refant=refant,
                       calmode="p", minsnr=3.0, gaintable=[ff["caltable"]], minblperant=4,
                       overwrite=True)
    timings["gaincal"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ap = tasks.applycal(vis, [ff["caltable"], gc["caltable"]], applymode="calflag")
    timings["applycal"] = time.perf_counter() - t0
    info = {"wrapper": "hitops.casa.tasks", "flagged_fraction": ap.get("flagged_fraction")}
except ImportError:
    import casatasks
    t0 = time.perf_counter()
    casatasks.fringefit(vis=vis, caltable=str(outdir / "fringefit.tbl"), solint="20s",
                        refant=refant, minsnr=3.0)
    timings["fringefit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    casatasks.gaincal(vis=vis, caltable=str(outdir / "gaincal.tbl"), solint="10s",
                      refant=refant, calmode="p", minsnr=3.0,
                      gaintable=[str(outdir / "fringefit.tbl")], minblperant=4)
    timings["gaincal"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    casatasks.applycal(vis=vis, gaintable=[str(outdir / "fringefit.tbl"),
                                           str(outdir / "gaincal.tbl")], applymode="calflag")
    timings["applycal"] = time.perf_counter() - t0
    info = {"wrapper": "casatasks"}
(outdir / "ffsc-timings.json").write_text(json.dumps({"timings_s": timings, **info}))
"""

# The recipe's imfit step (recipes/fpt-lib.yml, image-fit.imfit: cab hitops.casa.imfit)
# in its own process: CASA's log and stdout chatter stay out of the benchmark's output.
IMFIT_SCRIPT = """
import sys
from hitops.casa import imfit
image, dirty, label, half_width, max_abs_peak, outfile = sys.argv[1:7]
imfit(image, label=label, centre_half_width=int(half_width), fallback=True,
      fallback_image=dirty, max_abs_peak=float(max_abs_peak), outfile=outfile)
"""


@dataclass
class Row:
    """One line of the table: a column of a Measurement Set and what it cost."""

    key: str                      # short id, also the image / imfit label
    label: str                    # table label
    ms: str
    column: str
    wall: Optional[float] = None  # whole-process wall (s); None for raw and oracle
    cpu: Optional[float] = None
    rss: Optional[float] = None
    note: str = ""
    ratio: bool = True            # show the I/O-floor ratio
    tool_s: Optional[float] = None  # calibrate's own time_s (report), last run
    metrics: dict = field(default_factory=dict)
    image: dict = field(default_factory=dict)   # recovery, fit, imaging times


def available_trackers():
    """The wrap trackers ``hitops calibrate --tracker`` accepts (its schema's choices)."""
    import yaml

    schema = yaml.safe_load((ROOT / "hitops" / "schemas" / "calibrate.yml").read_text())
    return list(schema["inputs"]["tracker"].get("choices") or ["count"])


def segment_coherence(phase: np.ndarray, valid: np.ndarray, samples: int) -> float:
    """Mean over baselines of the mean C over ``samples``-long segments (>= half filled)."""
    n_bl, n_time = phase.shape[:2]
    n_seg = n_time // samples
    ph = phase[:, :n_seg * samples].reshape(n_bl, n_seg, samples, -1)
    ok = valid[:, :n_seg * samples].reshape(n_bl, n_seg, samples, -1)
    z = np.where(ok, np.exp(1j * ph), 0).sum(axis=2)
    n = ok.sum(axis=2)
    use = n >= samples // 2
    c = np.where(use, np.abs(z) / np.maximum(n, 1), np.nan)
    per_bl = np.nanmean(c.reshape(n_bl, -1), axis=1)
    return float(np.nanmean(per_bl))


def _centred(phase: np.ndarray, valid: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Phases minus the circular mean of their (baseline, group, correlation) cell."""
    n_bl, n_time, n_corr = phase.shape
    n_group = int(group.max()) + 1
    key = (np.arange(n_bl)[:, None] * n_group + group)[:, :, None] * n_corr + np.arange(n_corr)
    z = np.zeros(n_bl * n_group * n_corr, complex)
    np.add.at(z, key[valid], np.exp(1j * phase[valid]))
    return np.angle(np.exp(1j * phase) * np.exp(-1j * np.angle(z[key])))


def phase_metrics(vis: np.ndarray, valid: np.ndarray, present: np.ndarray, dt: float) -> dict:
    """Residual-phase rms (deg) with per-baseline and per-segment constants removed,
    C(60 s) and the usable fraction of the rows present."""
    phase = np.angle(vis)
    whole = np.zeros(present.shape, np.int64)
    # track segments: a new one after every gap (a station set or a row is missing)
    starts = present & ~np.concatenate([np.zeros((present.shape[0], 1), bool),
                                        present[:, :-1]], axis=1)
    segments = np.cumsum(starts, axis=1)
    out = {}
    for key, group in (("rms_deg", whole), ("rms_seg_deg", segments)):
        err = _centred(phase, valid, group)[valid]
        out[key] = float(np.degrees(np.sqrt(np.mean(err ** 2)))) if err.size else np.nan
    out["coherence_60s"] = segment_coherence(phase, valid, max(1, int(round(SEGMENT_S / dt))))
    out["usable"] = float(valid.sum() / max(1, present[:, :, None].repeat(valid.shape[2], 2).sum()))
    return out


def _truth_rows(truth, times, names, ant1, ant2) -> np.ndarray:
    """True 230 GHz troposphere phase phi_p - phi_q of each (time, ant1, ant2)."""
    t_idx = np.searchsorted(truth["time"], times - 1e-3)
    truth_names = [str(n) for n in truth["antenna_names_230"]]
    index = np.array([truth_names.index(str(n)) for n in names])
    phase = truth["phase_230"]
    return phase[index[ant1], t_idx] - phase[index[ant2], t_idx]


def evaluate(ms: str, column: str) -> dict:
    from hitops.diagnose.read import read_grid

    grid = read_grid(ms, [column], correlations="all")
    vis = grid.vis[column]
    valid = ~grid.flag & np.isfinite(vis) & (vis != 0)
    present = grid.scan >= 0
    return phase_metrics(vis, valid, present, grid.dt)


def write_oracle_column(ms: str, truth, column: str = ORACLE_COLUMN) -> None:
    """DATA with the simulator's true troposphere removed, into ``column`` (created,
    or rewritten on a rerun; DATA itself is never touched)."""
    from casacore import tables as pt

    with pt.table(f"{ms}/ANTENNA", ack=False) as ant:
        names = ant.getcol("NAME")
    with pt.table(ms, readonly=False, ack=False) as t:
        tropo = _truth_rows(truth, t.getcol("TIME"), names, t.getcol("ANTENNA1"),
                            t.getcol("ANTENNA2"))
        data = t.getcol("DATA")
        if column not in t.colnames():
            desc = t.getcoldesc("DATA")
            desc["name"] = column
            t.addcols(pt.makecoldesc(column, desc))
        t.putcol(column, data * np.exp(-1j * tropo)[:, None, None])


# ---------------------------------------------------------------- imaging (recipe's)

def recipe_imaging() -> dict:
    """The imaging and fit parameters of recipes/fpt-paper.yml's ``images`` step.

    Read from the recipe files themselves (fpt-paper.yml's defaults, the
    image-fit sub-recipe of fpt-lib.yml, the hitops.wsclean cab's defaults),
    so this benchmark images exactly as the recipe does.
    """
    import yaml

    def load(rel):
        return yaml.safe_load((ROOT / rel).read_text())

    try:
        paper = load("recipes/fpt-paper.yml")["fpt-paper"]["inputs"]
        lib = load("recipes/fpt-lib.yml")["lib"]["recipes"]["image-fit"]
        cab = load("cabs/wsclean.yml")["cabs"]["hitops.wsclean"]["inputs"]
        return {
            "size": int(paper["image_size"]["default"]),
            "scale": str(paper["image_scale"]["default"]),
            "niter": int(paper["niter"]["default"]),
            "threshold": float(paper["clean_threshold"]["default"]),
            "threads": int(paper["threads"]["default"]),
            "weight": str(lib["inputs"]["weight"]["default"]),
            "mgain": float(lib["steps"]["image"]["params"]["mgain"]),
            "gain": float(cab["gain"]["default"]),
            "pol": str(cab["pol"]["default"]),
            "fit_half_width": int(lib["inputs"]["fit_half_width"]["default"]),
            "max_abs_peak": float(lib["inputs"]["max_abs_peak"]["default"]),
        }
    except (KeyError, TypeError) as err:
        raise RuntimeError(f"cannot read the recipe's imaging parameters ({err!r}): "
                           "recipes/fpt-paper.yml, recipes/fpt-lib.yml or cabs/wsclean.yml "
                           "changed shape; update recipe_imaging()") from err


def wsclean_command(ms: str, column: str, name: str, p: dict) -> list:
    """The command the hitops.wsclean cab builds for the recipe's image step."""
    wsclean = shutil.which("wsclean") or "/usr/bin/wsclean"
    return [wsclean, "-name", name, "-data-column", column,
            "-size", str(p["size"]), str(p["size"]), "-scale", p["scale"],
            "-niter", str(p["niter"]), "-mgain", str(p["mgain"]), "-gain", str(p["gain"]),
            "-threshold", str(p["threshold"]), "-weight", p["weight"], "-pol", p["pol"],
            "-j", str(p["threads"]), "-no-update-model-required", ms]


def image_and_fit(rows, outdir: Path, input_peak: float, params: dict) -> dict:
    """Image every row's column, fit its peak, and fill ``row.image``; return timings."""
    from hitops.compare import compare

    outdir.mkdir(parents=True, exist_ok=True)
    fits, labels = [], []
    for row in rows:
        name = str(outdir / row.key)
        try:
            im = run_process(wsclean_command(row.ms, row.column, name, params), cwd=str(outdir))
            fit_file = outdir / f"{row.key}-imfit.json"
            fit = run_process([sys.executable, "-c", IMFIT_SCRIPT, f"{name}-image.fits",
                               f"{name}-dirty.fits", row.key, str(params["fit_half_width"]),
                               str(params["max_abs_peak"]), str(fit_file)], cwd=str(outdir))
        except RuntimeError as err:
            row.image = {"error": str(err).splitlines()[-1][:200]}
            print(f"imaging {row.key}: failed ({row.image['error']})", flush=True)
            continue
        row.image = {"wsclean_s": im["wall_s"], "imfit_s": fit["wall_s"]}
        fits.append(str(fit_file))
        labels.append(row.key)
        print(f"imaged {row.key}: wsclean {im['wall_s']:.1f} s, imfit {fit['wall_s']:.1f} s",
              flush=True)
    if not fits:
        return {}
    table = compare(fits, labels=labels, input_peak=input_peak, outdir=str(outdir),
                    name="peak-flux", overwrite=True)
    by_label = {r["label"]: r for r in table["rows"]}
    for row in rows:
        r = by_label.get(row.key)
        if r:
            row.image.update(recovery=r["recovery"], recovery_err=r["recovery_err"],
                             fit=r["fit"], note=r["note"], peak=r["peak_jy"])
    w = [row.image["wsclean_s"] for row in rows if "wsclean_s" in row.image]
    f = [row.image["imfit_s"] for row in rows if "imfit_s" in row.image]
    return {"n": len(w), "wsclean_median": median(w), "wsclean_min": min(w),
            "wsclean_max": max(w), "imfit_median": median(f), "total": sum(w) + sum(f)}


# ---------------------------------------------------------------- runs

def time_calibrate(cmd, repeats: int):
    timed = [run_process(cmd) for _ in range(repeats)]
    return (median([r["wall_s"] for r in timed]), median([r["cpu_s"] for r in timed]),
            max(r["peak_rss_mb"] for r in timed))


def tool_time(report_path: Path) -> Optional[float]:
    """calibrate's own timing of its last run (report ``time_s``: no interpreter start-up
    or imports)."""
    try:
        return float(json.loads(report_path.read_text())["time_s"])
    except (OSError, KeyError, ValueError, TypeError):
        return None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-casa", action="store_true",
                        help="skip FF+SC (CASA, ~2-6 min) and the n0 offset-step runs that need it")
    parser.add_argument("--no-imaging", action="store_true",
                        help="skip the WSClean images and imfit peak-flux recovery (~10-40 s "
                             "per column)")
    args = parser.parse_args(argv if argv is not None else [])
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="bench-methods-"))
    workdir.mkdir(parents=True, exist_ok=True)
    bindir = Path(sys.executable).parent
    hitops = str(bindir / "hitops")
    load = [("start", os.getloadavg()[0])]

    from hitops.simulate.scene import parse_scene

    input_peak = float(parse_scene("paper").flux["230"])
    ref_ms, tgt_ms = workdir / "sim-86.ms", workdir / "sim-230.ms"
    sim = run_process([hitops, "simulate", "paper", "--outdir", str(workdir), "--prefix", "sim",
                       "--save-truth", "--overwrite"])
    truth = dict(np.load(workdir / "sim-truth.npz"))
    from casacore import tables as pt

    with pt.table(str(tgt_ms), ack=False) as t:
        n_row = t.nrows()

    floors = measure_floors(workdir, ref_ms, tgt_ms, repeats=args.repeats,
                            names=("issue", "same_columns"))
    rows = [Row("raw", "raw (DATA, no calibration)", str(tgt_ms), "DATA"),
            Row("oracle", "oracle: true troposphere removed (truth .npz)", str(tgt_ms),
                ORACLE_COLUMN)]
    methods = [("cfpt", "CFPT", "cfpt", "count", "CFPT_DATA"),
               ("cwu", "CWU", "cwu", "count", "CWU_DATA")]
    trackers = available_trackers()
    methods += [(f"pwc-{tr}", f"PWC ({tr} tracker)", "pwc", tr, f"PWC_{tr.upper()}")
                for tr in trackers]
    for key, label, method, tracker, column in methods:
        cmd = [hitops, "calibrate", str(ref_ms), str(tgt_ms), "--method", method,
               "--tracker", tracker, "--output-column", column, "--overwrite",
               "--report", str(workdir / f"{column}.json")]
        try:
            wall, cpu, rss = time_calibrate(cmd, args.repeats)
        except RuntimeError as err:
            print(f"{label}: failed, skipped ({str(err).splitlines()[-1]})", flush=True)
            continue
        rows.append(Row(key, label, str(tgt_ms), column, wall, cpu, rss,
                        f"median of {args.repeats}",
                        tool_s=tool_time(workdir / f"{column}.json")))
        print(label, f"{wall:.2f} s", flush=True)
    load.append(("after the hitops runs", os.getloadavg()[0]))

    ffsc_note = "not run (--no-casa)"
    if not args.no_casa:
        ffsc_ms = workdir / "ffsc-230.ms"
        shutil.rmtree(ffsc_ms, ignore_errors=True)
        shutil.copytree(tgt_ms, ffsc_ms)
        ffsc_dir = workdir / "ffsc"
        ffsc_dir.mkdir(exist_ok=True)
        script = workdir / "ffsc.py"
        script.write_text(FFSC_SCRIPT)
        try:
            r = run_process([sys.executable, str(script), str(ffsc_ms), str(ffsc_dir), REFANTS],
                            cwd=str(ffsc_dir))
            info = json.loads((ffsc_dir / "ffsc-timings.json").read_text())
            steps = ", ".join(f"{k} {v:.0f} s" for k, v in info["timings_s"].items())
            ffsc_note = f"one run ({steps}; {info['wrapper']})"
            rows.append(Row("ffsc", "FF+SC (CASA fringefit 20 s + gaincal 10 s + applycal)",
                            str(ffsc_ms), "CORRECTED_DATA", r["wall_s"], r["cpu_s"],
                            r["peak_rss_mb"], ffsc_note, ratio=False))
        except RuntimeError as err:
            ffsc_note = f"failed: {str(err).splitlines()[-1]}"
            print("FF+SC", ffsc_note, flush=True)
        load.append(("after FF+SC", os.getloadavg()[0]))
        # the paper's PWC: the n0 offset step against FF+SC (as recipes/fpt-paper.yml)
        if any(row.key == "ffsc" for row in rows):
            for key, label, method, tracker, column in methods:
                if method == "cfpt":
                    continue   # CFPT has no n0 offset (docs/calibrate.md)
                cmd = [hitops, "calibrate", str(ref_ms), str(ffsc_ms), "--method", method,
                       "--tracker", tracker, "--output-column", f"{column}_N0", "--overwrite",
                       "--offset-reference-column", "CORRECTED_DATA",
                       "--report", str(workdir / f"{column}_N0.json")]
                try:
                    wall, cpu, rss = time_calibrate(cmd, args.repeats)
                except RuntimeError as err:
                    print(f"{label} + n0: failed, skipped ({str(err).splitlines()[-1]})",
                          flush=True)
                    continue
                rows.append(Row(f"{key}-n0", f"{label} + n0 offsets vs FF+SC", str(ffsc_ms),
                                f"{column}_N0", wall, cpu, rss,
                                f"median of {args.repeats}; needs FF+SC's CORRECTED_DATA first",
                                ratio=False, tool_s=tool_time(workdir / f"{column}_N0.json")))
                print(rows[-1].label, f"{wall:.2f} s", flush=True)
            load.append(("after the n0 runs", os.getloadavg()[0]))

    write_oracle_column(str(tgt_ms), truth)
    for row in rows:
        row.metrics = evaluate(row.ms, row.column)

    imaging = {}
    params = None
    if not args.no_imaging:
        params = recipe_imaging()
        imaging = image_and_fit(rows, workdir / "images", input_peak, params)
        load.append(("after imaging", os.getloadavg()[0]))

    floor = floors["issue"]["wall_s"]
    fair = floors["same_columns"]["wall_s"]
    markdown = report(rows, args, sim, n_row, floor, fair, load, imaging, params, input_peak)
    print(markdown)
    replace_section("methods", markdown)
    if not args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)


# ---------------------------------------------------------------- report

def _recovery_cell(row: Row) -> str:
    im = row.image
    if "recovery" not in im:
        return "failed" if "error" in im else "-"
    cell = f"{im['recovery']:.3f} ± {im['recovery_err']:.3f}"
    if im.get("fit") != "gaussian":
        cell += " (max-pixel: CLEAN diverged, dirty-image peak)" if "diverged" in im.get(
            "note", "") else f" ({im.get('note') or im.get('fit')})"
    return cell


def report(rows, args, sim, n_row, floor, fair, load, imaging, params, input_peak) -> str:
    lines = []
    for row in rows:
        m = row.metrics
        if row.wall is None:
            cost = "- | - | - | - | |"
        else:
            ratio = f"{row.wall / floor:.1f} / {row.wall / fair:.1f}" if row.ratio else "-"
            note = row.note
            if row.tool_s is not None:
                note += f"; tool's own time {row.tool_s:.2f} s"
            cost = f"{row.wall:.2f} | {row.cpu:.2f} | {row.rss:.0f} | {ratio} | {note} |"
        lines.append(f"| {row.label} | {m['rms_deg']:.1f} | {m['rms_seg_deg']:.1f} | "
                     f"{m['coherence_60s']:.3f} | {100 * m['usable']:.1f} | "
                     f"{_recovery_cell(row)} | {cost}")
    fig = plot(rows, PLOT_DIR / "methods_error_runtime.png", with_recovery=bool(imaging))
    by = {row.key: row for row in rows}
    rec = {k: r.image.get("recovery") for k, r in by.items()}
    reading = []
    pwc, oracle = by.get("pwc-count"), by["oracle"]
    if pwc:
        sigma_ref = np.sqrt(max(pwc.metrics["rms_deg"] ** 2 - oracle.metrics["rms_deg"] ** 2, 0))
        reading.append(
            f"PWC leaves {pwc.metrics['rms_deg']:.1f} deg rms against the oracle's thermal "
            f"{oracle.metrics['rms_deg']:.1f} deg: the excess, {sigma_ref:.1f} deg in quadrature, "
            "is the reference band's noise scaled by R (sigma_FPT^2 = sigma_t^2 + R^2 sigma_r^2), "
            "and CWU gives the same numbers, as the algebra says (same reference wrap count)")
    if "cfpt" in by:
        reading.append(f"CFPT's jumps of -117 deg at every 86 GHz wrap leave "
                       f"{by['cfpt'].metrics['rms_deg']:.0f} deg rms, barely below raw")
    ff = by.get("ffsc")
    if ff and pwc:
        reading.append(f"FF+SC reaches {ff.metrics['rms_deg']:.0f} deg rms and C = "
                       f"{ff.metrics['coherence_60s']:.2f} in {ff.wall:.0f} s, "
                       f"{ff.wall / pwc.wall:.0f}x PWC's whole-process time, and flags "
                       f"{100 * (1 - ff.metrics['usable']):.0f}% of the samples (intervals "
                       "without a gaincal solution)")
    n0 = by.get("pwc-count-n0")
    if n0 and pwc:
        reading.append(f"with the n0 step against FF+SC the same PWC leaves "
                       f"{n0.metrics['rms_deg']:.1f} deg on FF+SC's copy, whose flags remove "
                       f"{100 * (1 - n0.metrics['usable']):.0f}% of the samples")
    pairs = [(k, by[k], by[k + "-n0"]) for k in ("cwu", "pwc-count", "pwc-smooth", "pwc-antenna")
             if k in by and k + "-n0" in by and by[k].tool_s and by[k + "-n0"].tool_s]
    if pairs:
        reading.append("the n0 step (a first pass that compares with CORRECTED_DATA, then the "
                       "output pass) takes calibrate's own time (report time_s, no start-up) "
                       "from " + ", ".join(f"{a.tool_s:.2f} to {b.tool_s:.2f} s ({k})"
                                           for k, a, b in pairs)
                       + "; the rest of each whole-process wall is interpreter start-up, imports "
                       "and exit")
    reading = ("Reading: " + "; ".join(reading) + ".") if reading else ""

    if imaging:
        flux_text = recovery_text(by, rec, imaging, params, input_peak)
    elif not args.no_imaging:
        flux_text = "Peak-flux recovery: every image failed in this run (see its output)."
    else:
        flux_text = ("Peak-flux recovery was not measured in this run (`--no-imaging`); the "
                     "recipe run of the same scene (docs/paper-rerun.md) measured PWC "
                     f"{RECIPE_RECOVERY['pwc']} and FF+SC {RECIPE_RECOVERY['ffsc']} (paper: "
                     f"{PAPER_RECOVERY['pwc']} and {PAPER_RECOVERY['ffsc']}).")
    opts = " ".join(o for o, on in (("--no-casa", args.no_casa),
                                    ("--no-imaging", args.no_imaging)) if on)
    loads = ", ".join(f"{v:.1f} {when}" for when, v in load)
    return f"""## Error against run time: calibration methods on the paper's scene (issue 7)

Machine: {machine_line()}; 1-minute load average {loads} (shared machine, the
benchmark run under `nice -n 15`: wall times are upper bounds).  Scene: `hitops simulate paper --save-truth` ({sim['wall_s']:.1f} s),
{n_row} rows per band, RR/LL, 230 GHz source flux {input_peak:g} Jy.  Every run is a
whole process (benchmarks/_report.run_process); the I/O floors of this scene are
{floor:.2f} s (issue 2's: 2 x DATA read, 1 column written) and {fair:.2f} s (every
column calibrate reads), ratios in the table as calibrate wall / floor.
Run: `python -m benchmarks.bench_methods --repeats {args.repeats}{' ' + opts if opts else ''}`.

| method | residual phase error at 230 GHz, deg rms (constant per baseline removed) | same, constant per track segment removed | C(60 s), mean over baselines | usable samples (% of rows x corr) | peak-flux recovery (imfit peak / {input_peak:g} Jy) | wall (s) | CPU (s) | peak RSS (MB) | x I/O floor (issue / same columns) | runs |
|---|---|---|---|---|---|---|---|---|---|---|
{chr(10).join(lines)}

{reading}

{flux_text}

Residual phase error: arg V at 230 GHz minus the truth (phase 0: a point source at
the phase centre), each baseline's circular mean removed, rms over unflagged
samples of both correlations; the second error column removes a constant per
stretch of consecutive samples instead (a new stretch after every gap, e.g. a
station setting), which forgives a tracker that restarts its count after a gap.  The
oracle row removes the simulator's own troposphere phases and leaves thermal noise
only.  FF+SC and the "+ n0" rows are evaluated on FF+SC's copy of the set, with the
flags applycal (calflag) set where gaincal found no solution; the other hitops rows
flag only samples without a usable reference.

![error, coherence and peak-flux recovery against wall time]({fig.relative_to(PLOT_DIR.parent)})

Run: `python -m benchmarks.bench_methods [--workdir DIR] [--repeats N] [--no-casa] [--no-imaging]`.
"""


def recovery_text(by, rec, imaging, params, input_peak) -> str:
    p = params
    parts = [
        f"Peak-flux recovery: each column imaged with WSClean ({p['size']} x {p['size']} "
        f"pixels of {p['scale']}, {p['weight']} weighting, CLEAN to {p['threshold']:g} Jy or "
        f"{p['niter']} iterations, mgain {p['mgain']:g}, {p['threads']} threads: the "
        "parameters of recipes/fpt-paper.yml's images step, read from the recipe files), "
        f"the peak fitted by CASA imfit (hitops.casa.imfit, box +-{p['fit_half_width']} pixels "
        "about the phase centre; where CLEAN diverged, a fitted |peak| above "
        f"{p['max_abs_peak']:g} Jy/beam, the dirty image's brightest pixel, marked max-pixel, "
        "as the recipe does) and divided by the scene's "
        f"{input_peak:g} Jy by hitops.compare; the error is imfit's peak error (max-pixel: "
        f"the robust rms of the box).  Imaging is not part of any wall time: per image "
        f"WSClean took {imaging['wsclean_median']:.0f} s (median; {imaging['wsclean_min']:.0f}-"
        f"{imaging['wsclean_max']:.0f} s) and imfit {imaging['imfit_median']:.0f} s, "
        f"{imaging['total']:.0f} s for the {imaging['n']} images."]
    notes = []
    plain = [k for k in ("cwu", "pwc-count", "pwc-smooth", "pwc-antenna")
             if rec.get(k) is not None]
    n0 = [k + "-n0" for k in plain if rec.get(k + "-n0") is not None]
    if plain:
        diverged = [k for k in plain if by[k].image.get("fit") != "gaussian"]
        notes.append(
            "Without the n0 offset step the CWU/PWC columns keep a constant 2 pi eps n0 per "
            "baseline (n0: the reference wraps before the first sample of the scan; "
            "antenna-based with the antenna tracker, so its closure phases are right, but an "
            "image made without self-calibration needs the phases themselves), which the "
            "phase-error columns forgive but the image does not: "
            + ", ".join(f"{k} {rec[k]:.3f}" for k in plain)
            + (f" (CLEAN diverged on {', '.join(diverged)}: these are dirty-image maxima, "
               "about the weighted vector average of the visibilities, not deconvolved fits)"
               if diverged else ""))
    if n0:
        notes.append("with the offset step against FF+SC's CORRECTED_DATA, as the recipe and "
                     "the paper do: " + ", ".join(f"{k[:-3]} {rec[k]:.3f}" for k in n0))
    if rec.get("ffsc") is not None:
        best = rec.get("pwc-count-n0")
        notes.append(
            f"FF+SC {rec['ffsc']:.3f}" + (f" against PWC's {best:.3f}" if best else "")
            + f" (paper: PWC {PAPER_RECOVERY['pwc']}, FF+SC {PAPER_RECOVERY['ffsc']}; the "
            f"recipe run of the same scene, docs/paper-rerun.md: PWC "
            f"{RECIPE_RECOVERY['pwc']}, FF+SC {RECIPE_RECOVERY['ffsc']})")
    if rec.get("cfpt") is not None:
        notes.append(f"CFPT {rec['cfpt']:.3f}"
                     + (", the dirty image's maximum because CLEAN diverged"
                        if by["cfpt"].image.get("fit") != "gaussian" else "")
                     + f" (recipe: {RECIPE_RECOVERY['cfpt']}, CLEAN diverged there too)")
    if rec.get("oracle") is not None and rec.get("raw") is not None:
        notes.append(f"the oracle (thermal noise only) recovers {rec['oracle']:.3f}, raw data "
                     f"{rec['raw']:.3f}")
    return parts[0] + ("\n\n" + "; ".join(notes) + "." if notes else "")


def _short(row: Row) -> str:
    """Plot label: 'PWC count', 'PWC count +n0', 'FF+SC', 'CFPT'."""
    label = row.label
    n0 = " +n0" if row.key.endswith("-n0") else ""
    if label.startswith("PWC ("):
        return "PWC " + label[5:].split(" ")[0] + n0
    return label.split(" (")[0].split(" +")[0] + n0


def plot(rows, path: Path, with_recovery: bool = True) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    panels = [("rms_deg", "residual phase error at 230 GHz (deg rms)"),
              ("coherence_60s", "coherence factor C(60 s)")]
    if with_recovery:
        panels.append(("recovery", "peak-flux recovery (imfit peak / true flux)"))
    widths = [1.0] * len(panels) + [0.42]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(4.0 * len(panels) + 1.8, 4.2),
                             gridspec_kw={"width_ratios": widths})
    legend_ax, axes = axes[-1], axes[:-1]

    def value(row, key):
        return row.image.get("recovery") if key == "recovery" else row.metrics.get(key)

    # rows without a wall time (raw, oracle) are reference levels
    for row in rows:
        if row.wall is not None:
            continue
        for ax, (key, _) in zip(axes, panels):
            v = value(row, key)
            if v is None:
                continue
            ax.axhline(v, ls="--", lw=0.8, color="0.5")
            ax.text(0.98, v, row.label.split(":")[0].split(" (")[0], fontsize=7,
                    va="bottom", ha="right", color="0.35", transform=ax.get_yaxis_transform())
    base_colour = {}
    handles = []
    for row in [r for r in rows if r.wall is not None]:
        base = row.key[:-3] if row.key.endswith("-n0") else row.key
        colour = base_colour.setdefault(base, f"C{len(base_colour)}")
        marker = "s" if row.key.endswith("-n0") else ("D" if row.key == "ffsc" else "o")
        for ax, (key, _) in zip(axes, panels):
            v = value(row, key)
            if v is None:
                continue
            diverged = key == "recovery" and row.image.get("fit") != "gaussian"
            ax.plot(row.wall, v, marker, ms=7, color=colour,
                    mfc="none" if diverged else colour, mew=1.5)
        handles.append(Line2D([], [], ls="", marker=marker, color=colour, ms=7,
                              label=_short(row)))
    for ax, (key, ylabel) in zip(axes, panels):
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time, whole process (s)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_yscale("log")
    if with_recovery:
        axes[-1].set_ylim(-0.03, 1.08)
        if any(r.wall is not None and "recovery" in r.image and r.image.get("fit") != "gaussian"
               for r in rows):
            handles.append(Line2D([], [], ls="", marker="o", color="0.3", mfc="none", ms=7,
                                  mew=1.5, label="open: CLEAN diverged,\ndirty-image peak"))
    if any(r.key.endswith("-n0") for r in rows):
        handles.append(Line2D([], [], ls="", marker="s", color="0.3", ms=7,
                              label="+n0: offset step vs FF+SC\n(needs FF+SC first)"))
    legend_ax.axis("off")
    legend_ax.legend(handles=handles, loc="center left", fontsize=8, frameon=False)
    fig.suptitle("Paper scene (8 stations, 12 h, 1 s): phase error, coherence"
                 + (" and peak-flux recovery" if with_recovery else "")
                 + " of each calibration against its wall time", fontsize=10)
    save_figure(fig, path)
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
