"""``hitops diagnose`` on small Measurement Sets with known coherence.

Phases that alternate +a, -a from sample to sample give, over any segment
with an even number of samples, C = |cos a| exactly; so each baseline's
coherence factor, improvement, ranking, mean, median and per-antenna summary
are known in advance and checked against a hand computation.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import subprocess
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from hitops.diagnose import diagnose
from hitops.errors import ColumnError, InputError

from test_diagnose_helpers import build_ms

STATIONS = ["AP", "SM", "PV", "GL", "KC"]
PAIRS = [f"{a}-{b}" for a, b in combinations(STATIONS, 2)]
N_TIME = 600


def _alternating(a_per_bl, n_time=N_TIME, n_corr=2):
    """Phases +a, -a, +a, ... per baseline: C(T) = cos(a) for even segments."""
    sign = np.where(np.arange(n_time) % 2 == 0, 1.0, -1.0)
    return np.asarray(a_per_bl)[:, None, None] * sign[None, :, None] * np.ones((1, 1, n_corr))


# before: C = cos(a_before); after: C = cos(a_after).  Baselines with KC are
# barely improved, so KC is the one bad station.
C_BEFORE = np.array([0.50, 0.55, 0.60, 0.45, 0.52, 0.58, 0.40, 0.48, 0.62, 0.56])
C_AFTER = C_BEFORE * np.where(["KC" in p for p in PAIRS], np.linspace(1.02, 1.08, 10),
                              np.linspace(1.40, 1.50, 10))
C_BEST = np.minimum(C_AFTER * 1.2, 0.99)


@pytest.fixture(scope="module")
def known_ms(tmp_path_factory):
    path = tmp_path_factory.mktemp("diag") / "known.ms"
    phases = {"DATA": _alternating(np.arccos(C_BEFORE)),
              "CORRECTED_DATA": _alternating(np.arccos(C_AFTER)),
              "PWC_DATA": _alternating(np.arccos(C_BEST))}
    return build_ms(path, phases, STATIONS)


def _hand_improvement(before, after):
    return 100.0 * (after / before - 1.0)


def test_rankings_means_medians_and_antennas_match_hand_computation(known_ms, tmp_path):
    out = tmp_path / "out"
    summary = diagnose(known_ms, columns="DATA,CORRECTED_DATA,PWC_DATA", interval=60,
                       intervals="10,20,60,120", outdir=out)
    # per-baseline coherence factors are exactly cos(a)
    by_name = {rec["baseline"]: rec for rec in summary["baselines"]}
    for name, cb, ca, cp in zip(PAIRS, C_BEFORE, C_AFTER, C_BEST):
        cols = by_name[name]["columns"]
        assert cols["DATA"]["coherence_factor"] == pytest.approx(cb, abs=1e-6)
        assert cols["CORRECTED_DATA"]["coherence_factor"] == pytest.approx(ca, abs=1e-6)
        assert cols["PWC_DATA"]["coherence_factor"] == pytest.approx(cp, abs=1e-6)
        assert cols["DATA"]["n_segments"] == N_TIME // 60
    comps = {(c["before"], c["after"]): c for c in summary["comparisons"]}
    assert set(comps) == {("DATA", "CORRECTED_DATA"), ("DATA", "PWC_DATA"),
                          ("CORRECTED_DATA", "PWC_DATA")}
    comp = comps[("DATA", "CORRECTED_DATA")]
    pct = _hand_improvement(C_BEFORE, C_AFTER)
    order = np.argsort(pct)                      # worst first
    assert [r["baseline"] for r in comp["ranking"]] == [PAIRS[i] for i in order]
    assert [r["rank"] for r in comp["ranking"]] == list(range(1, 11))
    assert [r["improvement_pct"] for r in comp["ranking"]] == pytest.approx(pct[order], abs=1e-3)
    assert comp["mean_improvement_pct"] == pytest.approx(pct.mean(), abs=1e-3)
    assert comp["median_improvement_pct"] == pytest.approx(np.median(pct), abs=1e-3)
    assert comp["n_improved"] == 10 and comp["n_undefined"] == 0
    # C(T) is flat here, so "after" wins at every interval of the grid
    assert all(c["n_worse_at_some_interval"] == 0 for c in comps.values())
    # per antenna: median of its four baselines; KC stands out
    ants = {a["antenna"]: a for a in comp["antennas"]}
    for st in STATIONS:
        mine = [p for i, p in enumerate(pct) if st in PAIRS[i].split("-")]
        assert ants[st]["median_improvement_pct"] == pytest.approx(np.median(mine), abs=1e-3)
        assert ants[st]["n_baselines"] == 4
    assert comp["antennas"][0]["antenna"] == "KC"
    assert [a["antenna"] for a in comp["antennas"] if a["outlier"]] == ["KC"]
    # PWC beats FF+SC on every baseline: checkable from the JSON
    stored = json.loads((out / "summary.json").read_text())
    for rec in stored["baselines"]:
        assert (rec["columns"]["PWC_DATA"]["coherence_factor"]
                >= rec["columns"]["CORRECTED_DATA"]["coherence_factor"])
    assert all(r["improvement_pct"] >= 0 for r in
               next(c for c in stored["comparisons"]
                    if c["before"] == "CORRECTED_DATA")["ranking"])
    # the files hold the same ranking
    with open(out / "coherence-table.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["comparison"] == "CORRECTED_DATA vs DATA"]
    assert [r["baseline"] for r in rows] == [PAIRS[i] for i in order]
    text = (out / "coherence-table.txt").read_text()
    assert f"mean improvement {pct.mean():+.1f}%" in text
    assert f"median {np.median(pct):+.1f}%" in text
    assert "KC" in [line.split()[0] for line in text.splitlines() if "<-- outlier" in line]
    assert (out / "antenna-table.csv").exists()
    assert summary["outputs"]["summary_json"] == str(out / "summary.json")


def test_coherence_time_metric_reports_bounds(known_ms, tmp_path):
    """Alternating phases keep C(T) flat: above 1/e -> tau_c is a lower bound."""
    summary = diagnose(known_ms, columns="DATA,PWC_DATA", metric="coherence-time",
                       intervals="10,20,60,120", outdir=tmp_path)
    rec = summary["baselines"][0]
    assert rec["columns"]["DATA"]["tau_c_bound"] == ">"
    assert rec["columns"]["DATA"]["tau_c_s"] == 120.0
    comp = summary["comparisons"][0]
    # both are lower bounds: the improvement is undefined, with a note, never NaN
    assert all(r["improvement_pct"] is None for r in comp["ranking"])
    assert all("lower bound" in r["note"] for r in comp["ranking"])
    assert comp["mean_improvement_pct"] is None
    json.loads((tmp_path / "summary.json").read_text())   # valid JSON, no NaN


def test_fully_flagged_baseline_and_column_are_reported(tmp_path):
    rng = np.random.default_rng(5)
    st = STATIONS[:4]
    n_bl = 6
    phases = {"DATA": rng.normal(0, 1.0, (n_bl, N_TIME, 2)),
              "CORRECTED_DATA": rng.normal(0, 0.3, (n_bl, N_TIME, 2)),
              "PWC_DATA": np.zeros((n_bl, N_TIME, 2))}
    flag = np.zeros((n_bl, N_TIME, 2), bool)
    flag[2] = True                                        # AP-GL fully flagged
    amp = {"PWC_DATA": np.zeros((n_bl, N_TIME))}          # a column of zeros
    ms = build_ms(tmp_path / "flagged.ms", phases, st, flag=flag, amplitude=amp)
    summary = diagnose(ms, columns="DATA,CORRECTED_DATA,PWC_DATA", outdir=tmp_path / "o",
                       intervals="10,60")
    warnings = " ".join(summary["warnings"])
    assert "AP-GL" in warnings and "PWC_DATA has no usable sample" in warnings
    comp = summary["comparisons"][0]          # CORRECTED_DATA vs DATA
    last = comp["ranking"][-1]
    assert last["baseline"] == "AP-GL" and last["improvement_pct"] is None
    assert "no usable sample" in last["note"]
    assert comp["n_defined"] == 5
    pwc = [c for c in summary["comparisons"] if c["after"] == "PWC_DATA"]
    assert all(r["improvement_pct"] is None and "PWC_DATA" in r["note"]
               for c in pwc for r in c["ranking"])
    text = (tmp_path / "o" / "coherence-table.txt").read_text()
    table_rows = [line for line in text.splitlines() if re.match(r"^\s+\d+\s+\w+-\w+", line)]
    assert len(table_rows) == 18 and "n/a" in text
    assert not any(re.search(r"\bnan\b", row.lower()) for row in table_rows)
    json.loads((tmp_path / "o" / "summary.json").read_text())


def test_bad_input_gives_clear_messages(known_ms, tmp_path):
    with pytest.raises(ColumnError, match="NOPE_DATA.*not found"):
        diagnose(known_ms, columns="DATA,NOPE_DATA", outdir=None)
    with pytest.raises(InputError, match="longer than the track"):
        diagnose(known_ms, interval=5000, outdir=None)
    with pytest.raises(InputError, match="station 'XX'"):
        diagnose(known_ms, baselines="AP-XX", outdir=None)
    with pytest.raises(InputError, match="correlation"):
        diagnose(known_ms, correlations="XY", outdir=None)
    with pytest.raises(InputError, match="unknown plot"):
        diagnose(known_ms, plots="phase,pretty", outdir=tmp_path)
    with pytest.raises(InputError, match="--interval"):
        diagnose(known_ms, interval=-1, outdir=None)
    # grid points beyond the track are dropped with a warning, not NaN
    summary = diagnose(known_ms, intervals="10,60,5000", outdir=None)
    assert summary["intervals_s"] == [10.0, 60.0]
    assert any("5000" in w for w in summary["warnings"])
    # and intervals shorter than the sampling interval (one sample, C = 1) too
    summary = diagnose(known_ms, intervals="0.5,10", outdir=None)
    assert summary["intervals_s"] == [10.0, 60.0]
    assert any("0.5" in w and "shorter" in w for w in summary["warnings"])
    # selections: one station, one baseline, one correlation
    summary = diagnose(known_ms, baselines="KC", correlations="LL", outdir=None)
    assert [r["baseline"] for r in summary["baselines"]] == ["AP-KC", "SM-KC", "PV-KC", "GL-KC"]
    assert summary["correlations"] == ["LL"]


def test_everything_flagged_is_an_error(tmp_path):
    phases = {"DATA": np.zeros((1, 100, 2)), "CORRECTED_DATA": np.zeros((1, 100, 2))}
    ms = build_ms(tmp_path / "dead.ms", phases, ["AP", "SM"],
                  flag=np.ones((1, 100, 2), bool))
    with pytest.raises(InputError, match="every sample"):
        diagnose(ms, interval=10, intervals="10", outdir=None)


def _coloured_fraction(png: Path) -> float:
    """Fraction of saturated (non-grey) pixels: data, not frames, ticks or text."""
    from matplotlib.image import imread

    img = imread(png)[..., :3]
    return float(np.mean(img.max(axis=-1) - img.min(axis=-1) > 0.2))


def _has_colour(png: Path, rgb, tol=0.08) -> bool:
    from matplotlib.image import imread

    img = imread(png)[..., :3]
    return bool(np.any(np.all(np.abs(img - np.asarray(rgb)) < tol, axis=-1)))


def test_plots_have_panels_wrap_markers_and_pixels(tmp_path):
    """Phase, C(T) and (u,v) plots of a 3-station MS with a reference band."""
    from matplotlib.colors import to_rgb

    from hitops.diagnose import plots as P
    from hitops.diagnose.metrics import compute_coherence, parse_intervals
    from hitops.diagnose.read import read_grid
    from hitops.diagnose.wraps import reference_wraps

    rng = np.random.default_rng(11)
    st = ["PV", "PB", "KP"]
    n_time = 900
    t = np.arange(n_time)
    # reference band: constant rate on every baseline, 1/150 Hz -> wraps every 150 s
    ref_phase = (2 * np.pi * t / 150.0 + np.pi / 2)[None, :, None] * np.ones((3, 1, 2))
    ref = build_ms(tmp_path / "ref.ms", {"DATA": ref_phase}, st, freq_hz=86e9)
    raw = np.cumsum(rng.normal(0, 0.2, (3, n_time, 2)), axis=1)
    target = build_ms(tmp_path / "t.ms", {"DATA": raw,
                                          "CFPT_DATA": rng.normal(0, 0.5, (3, n_time, 2)),
                                          "PWC_DATA": rng.normal(0, 0.2, (3, n_time, 2))}, st)
    out = tmp_path / "out"
    summary = diagnose(target, columns="DATA,CFPT_DATA,PWC_DATA", intervals="log:1:600:12",
                       ref_ms=ref, outdir=out, plots="phase,coherence,uv")
    # wraps of a phase ramp starting at pi/2 with period 150 s over 900 s: at 75 + 150k s
    expected_wraps = len(range(75, n_time, 150))
    assert summary["reference_wraps"]["PV-PB"] == {"RR": expected_wraps, "LL": expected_wraps}
    # white noise of 0.5 rad loses to a slow random walk at short T: reported per interval
    cfpt = next(c for c in summary["comparisons"] if c["after"] == "CFPT_DATA")
    assert all(r["worse_at_s"] and min(r["worse_at_s"]) < 10 for r in cfpt["ranking"])
    assert "CFPT_DATA has lower C(T) than DATA at some interval" in \
        (out / "coherence-table.txt").read_text()
    names = sorted(Path(p).name for p in summary["outputs"]["plots"])
    assert names == sorted([f"phase-{b}.png" for b in ("PV-PB", "PV-KP", "PB-KP")]
                           + [f"coherence-{b}.png" for b in ("PV-PB", "PV-KP", "PB-KP")]
                           + ["coherence-all.png", "uv-coverage.png"])
    for p in summary["outputs"]["plots"]:
        assert _coloured_fraction(Path(p)) > 0.005, p
    # every column's colour is drawn in the phase and coherence plots
    for name in ("phase-PV-PB.png", "coherence-PV-PB.png"):
        for colour in P.COLOURS[:3]:
            assert _has_colour(out / "plots" / name, to_rgb(colour)), (name, colour)
    blank, (ax,) = P.new_figure(1)
    ax.set_xlabel("time (h)")
    blank.savefig(tmp_path / "blank.png")
    assert _coloured_fraction(tmp_path / "blank.png") == 0.0   # the pixel test can fail

    # panel counts and wrap markers, from the figure objects
    data = read_grid(target, ["DATA", "CFPT_DATA", "PWC_DATA"], want_uvw=True)
    res = compute_coherence(data.vis_stack, ["DATA", "CFPT_DATA", "PWC_DATA"], data.flag,
                            data.times, data.scan, data.dt, parse_intervals("log:1:600:12"),
                            60.0, corr_names=data.corr_names)
    wraps, _ = reference_wraps(str(ref), data)
    fig = P.phase_figure(data, 0, ["DATA", "CFPT_DATA", "PWC_DATA"], wrap_times=wraps["PV-PB"])
    assert len(fig.axes) == 2                              # RR and LL
    for ax in fig.axes:
        assert len(ax.lines) == 3                          # one per column
        assert len(ax.collections[0].get_segments()) == expected_wraps
        assert "deg" in ax.get_ylabel()
    assert "(h)" in fig.axes[-1].get_xlabel()
    records = summary["baselines"]
    assert len(P.coherence_overview(res, data.baseline_names).axes) == 3
    cfig = P.coherence_figure(res, 0, "PV-PB", records)
    assert cfig.axes[0].get_xscale() == "log" and "T (s)" in cfig.axes[0].get_xlabel()
    ufig = P.uv_figure(data, res, records)
    data_axes = [ax for ax in ufig.axes if ax.get_label() != "<colorbar>"]
    assert len(data_axes) == 2                             # CFPT/DATA and PWC/DATA
    assert all("G$\\lambda$" in ax.get_xlabel() for ax in data_axes)


def test_cli_writes_fixed_outputs_and_exits_2_on_bad_input(known_ms, tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=os.environ.get(
        "NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".venv" / "numba-cache")))
    hitops = str(Path(sys.executable).with_name("hitops"))
    out = tmp_path / "cli"
    done = subprocess.run([hitops, "diagnose", str(known_ms), "--columns",
                           "DATA,CORRECTED_DATA,PWC_DATA", "--interval", "60", "--intervals",
                           "10,60", "--outdir", str(out)], capture_output=True, text=True,
                          env=env)
    assert done.returncode == 0, done.stderr
    for name in ("summary.json", "coherence-table.csv", "coherence-table.txt",
                 "antenna-table.csv"):
        assert (out / name).stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["columns"] == ["DATA", "CORRECTED_DATA", "PWC_DATA"]
    bad = subprocess.run([hitops, "diagnose", str(known_ms), "--columns", "DATA,MISSING",
                          "--outdir", str(out)], capture_output=True, text=True, env=env)
    assert bad.returncode == 2
    assert "MISSING" in bad.stderr and "Traceback" not in bad.stderr


def test_reference_wraps_match_baselines_by_station_name(tmp_path):
    """The reference MS lists the stations in another order: wraps still land right."""
    from hitops.diagnose.read import read_grid
    from hitops.diagnose.wraps import reference_wraps

    n_time = 600
    t = np.arange(n_time)
    # target PV-PB, PV-KP, PB-KP; reference stations reversed: KP-PB, KP-PV, PB-PV
    periods = {"KP-PB": 100.0, "KP-PV": 200.0, "PB-PV": 300.0}
    phase0 = np.pi / 2 + 0.05      # keeps every sample off the +-pi boundary
    ref_phase = np.stack([(2 * np.pi * t / p + phase0)[:, None] * np.ones((1, 2))
                          for p in periods.values()])
    ref = build_ms(tmp_path / "ref.ms", {"DATA": ref_phase}, ["KP", "PB", "PV"], freq_hz=86e9)
    target = build_ms(tmp_path / "t.ms", {"DATA": np.zeros((3, n_time, 2))},
                      ["PV", "PB", "KP"])
    data = read_grid(target, ["DATA"])
    wraps, warnings = reference_wraps(str(ref), data)
    assert not warnings
    expect = {"PV-PB": 300.0, "PV-KP": 200.0, "PB-KP": 100.0}
    for name, period in expect.items():
        times = wraps[name]["RR"] - data.times[0]
        # first sample at or past the crossing of +pi, then one wrap per period
        first = math.ceil(period * (np.pi - phase0) / (2 * np.pi))
        assert np.allclose(times, np.arange(first, n_time, period)), name
