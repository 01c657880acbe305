"""The n0 offset step against a model (issue 16): ``--offset-model point|COLUMN``.

With ``--tracker antenna`` the integers are solved per antenna and segment on the
2 pi eps k lattice with every baseline at once (hitops.calibrate.lattice); with the
baseline trackers the step falls back to the per-baseline choice against the model.
Scenes from hitops.calibrate.synthetic.make_pair with ``ref_offset_scale=0`` (a
purely antenna-based reference band, as a point source gives), so a noiseless
output with the right integers equals the source phase exactly.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate
from hitops.calibrate.synthetic import add_column, make_pair, wrap
from hitops.errors import InputError
from ms_columns import col, put  # tests/ is on sys.path (rootdir-relative)

EPS = 230.0 / 86.0 - 2


def run(truth, column="OUT", **kw):
    rep = calibrate(truth.ref_ms, truth.target_ms, output_column=column, overwrite=True, **kw)
    return col(truth.target_ms, column), rep


def late_station_pair(path, **kw):
    """4 stations, GL (index 3) joins the reference band after 250 s (tests/test_antenna.py's
    scene, with a purely antenna-based reference band)."""
    args = dict(n_ant=4, n_time=700, step_rad=0.12, drift_rad=0.06, seed=11,
                corr_types=("RR", "LL"), phase_offset_rad=1.0, ref_offset_scale=0.0)
    args.update(kw)
    truth = make_pair(path, **args)
    flag = col(truth.ref_ms, "FLAG")
    t_idx = np.rint(truth.time - truth.time.min()).astype(int)
    flag[((truth.ant1 == 3) | (truth.ant2 == 3)) & (t_idx < 250)] = True
    put(truth.ref_ms, "FLAG", flag)
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    return truth


def lattice_integer(y):
    """e in [-21, 21] with 2 pi eps e = y (mod 2 pi), per element."""
    k = np.arange(43)
    e = k[np.argmin(np.abs(wrap(np.asarray(y)[..., None] - wrap(2 * np.pi * EPS * k))), axis=-1)]
    return np.where(e > 21, e - 43, e)


def closures(truth, phase):
    """Closure phases (rad) of per-row phases over every triangle, per time and correlation."""
    n_ant = int(max(truth.ant1.max(), truth.ant2.max())) + 1
    times = np.unique(truth.time)
    t_idx = np.searchsorted(times, truth.time)
    grid = np.full((n_ant, n_ant, times.size, phase.shape[1]), np.nan)
    grid[truth.ant1, truth.ant2, t_idx] = phase
    out = []
    for p, q, r in itertools.combinations(range(n_ant), 3):
        out.append(grid[p, q] + grid[q, r] - grid[p, r])
    return np.array(out)


def test_late_station_true_integers_and_closures_kept(tmp_path):
    truth = late_station_pair(tmp_path)
    before, rep0 = run(truth, column="NOSTEP", tracker="antenna", refant="PV")
    flag = col(truth.target_ms, "FLAG")[:, 0, :]
    valid = ~flag
    resid0 = wrap(np.angle(before[:, 0, :]) - truth.source_phase)
    assert np.degrees(np.abs(resid0[valid])).max() > 100      # GL's baselines carry 2 pi eps k
    # the truth: GL's count error relative to PV, read off the output without the step
    gl_pv = (truth.ant1 == 2) & (truth.ant2 == 3) & valid[:, 0]
    k_true = np.unique(lattice_integer(resid0[gl_pv, 0]))
    assert k_true.size == 1 and k_true[0] != 0
    after, rep = run(truth, column="STEP", tracker="antenna", refant="PV",
                     offset_model="MODEL_DATA")
    assert np.array_equal(col(truth.target_ms, "FLAG")[:, 0, :], flag)
    resid = wrap(np.angle(after[:, 0, :]) - truth.source_phase)
    assert np.max(np.abs(resid[valid])) < 1e-3        # every baseline and sample (complex64)
    step = rep["offset_step"]
    assert step["solve"] == "antenna lattice" and step["model"] == "MODEL_DATA"
    assert step["per"] == "segment" and step["applied_to"] == ["pwc"]
    by_ant = {(e["antenna"], e["correlation"]): e for e in step["antennas"]}
    assert len(by_ant) == 8
    for c in ("RR", "LL"):
        assert by_ant[("PV", c)]["reference"] and by_ant[("PV", c)]["k"] == 0
        # PV-GL carries 2 pi eps e; the step adds 2 pi eps (k_PV - k_GL) = -2 pi eps e
        assert by_ant[("GL", c)]["k"] == k_true[0]
        assert by_ant[("AP", c)]["k"] == 0 and by_ant[("SM", c)]["k"] == 0
        for e in (by_ant[(a, c)] for a in ("AP", "SM", "PV", "GL")):
            assert e["residual_deg"] < 0.05 and e["margin_deg"] > 8.0 and not e["ambiguous"]
    assert [s["method"] for s in step["solves"]] == ["exhaustive", "exhaustive"]
    assert all(s["coherence"] > 0.9999 for s in step["solves"])
    # closure phases: the per-baseline integers close exactly (so the phase added by the
    # step closes to float64 rounding), and the written output keeps the target's closures
    # to the precision of its complex64 storage
    n_ant = 4
    d = {}
    for e in step["series"]:
        d[(e["baseline"], e["correlation"])] = e["k"]
    names = ["AP", "SM", "PV", "GL"]
    for c in ("RR", "LL"):
        for p, q, r in itertools.combinations(range(n_ant), 3):
            k_close = (d[(f"{names[p]}-{names[q]}", c)] + d[(f"{names[q]}-{names[r]}", c)]
                       - d[(f"{names[p]}-{names[r]}", c)])
            assert k_close == 0
            assert abs(math.remainder(2 * math.pi * EPS * k_close, 2 * math.pi)) < 1e-9
    ok_rows = valid.all(axis=1)
    cl0 = closures(truth, np.where(ok_rows[:, None], np.angle(before[:, 0, :]), np.nan))
    cl1 = closures(truth, np.where(ok_rows[:, None], np.angle(after[:, 0, :]), np.nan))
    fin = np.isfinite(cl0)
    assert fin.sum() > 1000
    assert np.max(np.abs(wrap(cl1[fin] - cl0[fin]))) < 2e-6


def test_point_model_and_chunked_runs_agree(tmp_path):
    """--offset-model point on a point source at the phase centre; several scans; the
    one-chunk run (first pass kept, shifted) equals the chunked run (two passes)."""
    truth = make_pair(tmp_path, n_ant=5, n_time=900, n_scans=3, step_rad=0.1, drift_rad=0.05,
                      seed=4, corr_types=("RR", "LL"), phase_offset_rad=1.3,
                      ref_offset_scale=0.0, sigma_ref=0.05, sigma_target=0.05)
    data = col(truth.target_ms, "DATA")
    put(truth.target_ms, "DATA", (data * np.exp(-1j * truth.source_phase)[:, None, :])
        .astype(np.complex64))                         # the source: a point at the centre
    out, rep = run(truth, tracker="antenna", offset_model="point")
    valid = ~col(truth.target_ms, "FLAG")[:, 0, :]
    resid = np.degrees(np.abs(wrap(np.angle(out[:, 0, :]))))
    # thermal noise only (R x reference noise + target noise, a few degrees)
    assert np.median(resid[valid]) < 5
    for a1, a2 in set(zip(truth.ant1.tolist(), truth.ant2.tolist())):
        sel = (truth.ant1 == a1) & (truth.ant2 == a2)
        for c in range(2):
            x = out[sel, 0, c][valid[sel, c]]
            assert abs(np.mean(x / np.abs(x))) > 0.99          # whole-track coherence
    step = rep["offset_step"]
    assert step["model"] == "point" and len(step["solves"]) == 3 * 2
    assert rep["chunks"] == 1 and "offset_solve" in rep["timings_s"]
    out_chunked, rep_chunked = run(truth, column="OUT2", tracker="antenna", offset_model="point",
                                   chunk_rows=1000)
    assert rep_chunked["chunks"] > 3
    assert [(e["antenna"], e["correlation"], e["scan"], e["k"]) for e in step["antennas"]] == \
        [(e["antenna"], e["correlation"], e["scan"], e["k"])
         for e in rep_chunked["offset_step"]["antennas"]]
    assert np.max(np.abs(np.angle(out_chunked[:, 0, :] * np.conj(out[:, 0, :]))[valid])) < 1e-5
    # without the step the same output carries the constants, and the run says so last
    no_step, rep_ns = run(truth, column="OUT3", tracker="antenna")
    assert rep_ns["offset_step"]["warning"] and "OUT3" in rep_ns["offset_step"]["warning"]
    assert step["warning"] is None


def test_baseline_trackers_fall_back_to_the_per_baseline_choice(tmp_path):
    truth = make_pair(tmp_path, n_time=300, phase_offset_rad=2.5, seed=1, ref_offset_scale=0.0)
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    for tracker in ("count", "smooth"):
        out, rep = run(truth, tracker=tracker, offset_model="MODEL_DATA")
        assert np.max(np.abs(wrap(np.angle(out[:, 0, :]) - truth.source_phase))) < 1e-4
        step = rep["offset_step"]
        assert step["solve"] == "baseline" and step["antennas"] == [] and step["solves"] == []
        assert step["per"] == ("scan" if tracker == "count" else "segment")
        assert any(e["k"] != 0 for e in step["series"])


def test_no_step_warning_is_among_the_last_lines(tmp_path, caplog):
    truth = make_pair(tmp_path, n_time=100, seed=2, corr_types=("RR",))
    with caplog.at_level("INFO", logger="hitops"):
        calibrate(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    last = [r for r in caplog.records if r.name.startswith("hitops")][-2:]
    assert "wrote PWC_DATA, CFPT_DATA" in last[0].getMessage()
    assert last[1].levelname == "WARNING"
    msg = last[1].getMessage()
    assert "PWC_DATA carries a constant 2 pi eps n0 per baseline" in msg
    assert "--offset-model point" in msg and "self-calibrate" in msg
    report = json.loads((truth.target_ms.parent / "target.ms.hitops-calibrate.json").read_text())
    assert report["offset_step"]["warning"] == msg
    caplog.clear()
    with caplog.at_level("INFO", logger="hitops"):
        calibrate(truth.ref_ms, truth.target_ms, method="cfpt", overwrite=True)
    assert "no n0 offset step ran" not in caplog.text            # CFPT has no n0
    with caplog.at_level("INFO", logger="hitops"):
        calibrate(truth.ref_ms, truth.target_ms, method="pwc", ratio=3.0, overwrite=True)
    assert "no n0 offset step ran" not in caplog.text            # integer R has none


@pytest.mark.parametrize("kwargs, match", [
    (dict(offset_model="point", offset_reference_column="DATA"), "give one"),
    (dict(offset_model="MODEL_DATA"), "MODEL_DATA"),
])
def test_bad_model_options_leave_the_set_unchanged(tmp_path, kwargs, match):
    truth = make_pair(tmp_path, n_time=50, seed=3, corr_types=("RR",))
    before = set(pt.table(str(truth.target_ms), ack=False).colnames())
    with pytest.raises(Exception, match=match):
        calibrate(truth.ref_ms, truth.target_ms, **kwargs)
    assert set(pt.table(str(truth.target_ms), ack=False).colnames()) == before


def test_model_column_is_not_an_output(tmp_path):
    truth = make_pair(tmp_path, n_time=50, seed=3, corr_types=("RR",))
    add_column(truth.target_ms, "MODEL_DATA", np.exp(1j * truth.source_phase)[:, None, :])
    with pytest.raises(InputError, match="input or flag column"):
        calibrate(truth.ref_ms, truth.target_ms, offset_model="MODEL_DATA",
                  output_column="MODEL_DATA", overwrite=True)
