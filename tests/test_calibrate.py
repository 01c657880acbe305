"""hitops calibrate on small synthetic Measurement Set pairs with a known troposphere.

Each test takes its own copy of a pair (hitops.testing.make_pair, through the
``new_pair`` fixture of tests/conftest.py), runs the tool and checks the output
against what the paper's algebra predicts.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.testing import (DEFAULT_NAMES, PairSpec, Signal, Storage, Troposphere, add_column,
                            expected_pwc_phase, wrap)
from ms_columns import col  # tests/ is on sys.path (rootdir-relative)


def out_phase(ms, name="PWC_DATA"):
    return np.angle(col(ms, name)[:, 0, :]).astype(np.float64)


def true_wraps(truth):
    """n(t): integer ambiguity of the wrapped reference phase (wrapped = true + 2*pi*n)."""
    return np.rint((wrap(truth.ref_phase_true) - truth.ref_phase_true) / (2 * np.pi)).astype(int)


def series(truth, values, bl_ant=(0, 1), corr=0):
    """One baseline's values in time order."""
    sel = (truth.ant1 == bl_ant[0]) & (truth.ant2 == bl_ant[1])
    order = np.argsort(truth.time[sel])
    return values[sel][order, corr]


@pytest.mark.parametrize("ratio,jump_deg", [(230 / 86, -117.209), (2.5, 180.0), (340 / 255, 120.0)])
def test_cfpt_jumps_by_2pi_eps_at_every_reference_wrap(new_pair, ratio, jump_deg):
    truth = new_pair(PairSpec(ratio=ratio, n_time=400, seed=3))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="cfpt")
    residual = wrap(out_phase(truth.target_ms, "CFPT_DATA") - truth.source_phase)
    n = true_wraps(truth)
    eps = ratio - math.floor(ratio)
    checked = 0
    for a1, a2 in [(0, 1), (1, 3), (0, 2)]:
        for c in range(2):
            r = series(truth, residual, (a1, a2), c)
            dn = np.diff(series(truth, n, (a1, a2), c))
            step = np.degrees(wrap(np.diff(r)))
            # a jump of -2*pi*eps*dn (mod 2*pi) exactly where the reference wraps ...
            expected = np.degrees(wrap(-2 * np.pi * eps * dn[dn != 0]))
            assert np.allclose(np.abs(wrap(np.radians(step[dn != 0] - expected))), 0, atol=1e-4)
            assert np.allclose(np.abs(wrap(np.radians(np.abs(step[dn != 0]) - abs(jump_deg)))), 0,
                               atol=1e-4)
            # ... and nowhere else
            assert np.all(np.abs(step[dn == 0]) < 1e-3)
            checked += int(np.count_nonzero(dn))
    assert checked >= 10, "the scene must wrap often enough to test anything"


def test_pwc_is_truth_up_to_n0_and_the_offset_step_removes_it(tmp_path, new_pair):
    truth = new_pair(PairSpec(n_time=300, seed=1, troposphere=Troposphere(phase_offset_rad=2.5)))
    n0_expected = expected_pwc_phase(truth)
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc")
    pwc = out_phase(truth.target_ms)
    assert np.max(np.abs(wrap(pwc - n0_expected))) < 1e-5
    # the constant offset is really there on some baselines (n0 != 0) ...
    assert np.max(np.abs(wrap(pwc - truth.source_phase))) > 0.5
    # ... and a reference calibration (a noisy "FF+SC" CORRECTED_DATA) removes it
    rng = np.random.default_rng(0)
    reference = np.exp(1j * (truth.source_phase + rng.normal(0, 0.3, truth.source_phase.shape)))
    add_column(truth.target_ms, "CORRECTED_DATA", reference)
    report_path = tmp_path / "offsets.json"
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", overwrite=True,
              offset_reference_column="CORRECTED_DATA", report=str(report_path))
    pwc = out_phase(truth.target_ms)
    assert np.max(np.abs(wrap(pwc - truth.source_phase))) < 1e-5
    report = json.loads(report_path.read_text())
    series_ = report["offset_step"]["series"]
    assert len(series_) == 6 * 2
    n0 = true_wraps(truth)
    for entry in series_:
        a1, a2 = ("AP", "SM", "PV", "GL").index(entry["baseline"][:2]), ("AP", "SM", "PV", "GL").index(entry["baseline"][3:])
        c = ["RR", "LL"].index(entry["correlation"])
        assert entry["k"] == series(truth, n0, (a1, a2), c)[0]
        assert entry["residual_deg"] < 2.0 and not entry["ambiguous"]
    assert any(e["k"] != 0 for e in series_)


def test_offset_step_k_is_bounded(new_pair):
    truth = new_pair(PairSpec(n_time=200, seed=1, troposphere=Troposphere(phase_offset_rad=2.5)))
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase))
    report = calibrate_flat(truth.ref_ms, truth.target_ms, offset_reference_column="CORRECTED_DATA",
                       max_offset_wraps=0)
    assert all(e["k"] == 0 for e in report["offset_step"]["series"])


def test_cwu_equals_pwc(new_pair):
    truth = new_pair(PairSpec(n_time=300, seed=5, troposphere=Troposphere(phase_offset_rad=1.7),
                              signal=Signal(sigma_target=0.4)))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cwu")
    pwc = col(truth.target_ms, "PWC_DATA")
    cwu = col(truth.target_ms, "CWU_DATA")
    assert np.max(np.abs(wrap(np.angle(pwc) - np.angle(cwu)))) < 1e-5
    assert np.allclose(np.abs(cwu), np.abs(col(truth.target_ms, "DATA")), rtol=1e-6)


def test_integer_ratio_all_three_agree(new_pair):
    truth = new_pair(PairSpec(ratio=3.0, n_time=300, seed=2,
                              troposphere=Troposphere(phase_offset_rad=2.5)))
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu")
    assert report["eps"] == 0.0 and report["r"] == 3
    for name in ("PWC_DATA", "CFPT_DATA", "CWU_DATA"):
        assert np.max(np.abs(wrap(out_phase(truth.target_ms, name) - truth.source_phase))) < 1e-4


def test_thermal_noise_residual_variance(new_pair):
    sigma_r_cpt, sigma_t_cpt, ref_amp, tgt_amp = 0.03, 0.08, 1.1, 1.0
    truth = new_pair(PairSpec(n_time=3000, seed=11,
                              troposphere=Troposphere(step_rad=0.05, drift_rad=0.02),
                              signal=Signal(sigma_ref=sigma_r_cpt, sigma_target=sigma_t_cpt,
                                            ref_amp=ref_amp, target_amp=tgt_amp)))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc")
    residual = wrap(out_phase(truth.target_ms) - expected_pwc_phase(truth))
    # n0 may differ from the noise-free count where a series starts near +-pi: take out
    # each series' circular mean before measuring the scatter
    key = truth.ant1 * 10 + truth.ant2
    centred = np.empty_like(residual)
    for k in np.unique(key):
        sel = key == k
        mean = np.angle(np.exp(1j * residual[sel]).mean(axis=0))
        centred[sel] = wrap(residual[sel] - mean)
    sigma_r, sigma_t = sigma_r_cpt / ref_amp, sigma_t_cpt / tgt_amp
    predicted = sigma_t ** 2 + truth.ratio ** 2 * sigma_r ** 2
    measured = float(np.var(centred))
    assert measured == pytest.approx(predicted, rel=0.05)
    # and R^2 sigma_r^2 really matters here (the test would fail without it)
    assert abs(measured - sigma_t ** 2) > 0.2 * predicted


def test_reordered_rows_and_swapped_antennas_give_the_same_answer(tmp_path, new_pair):
    spec = PairSpec(n_time=200, seed=4, corr_types=("RR", "RL", "LR", "LL"),
                    troposphere=Troposphere(phase_offset_rad=2.0))
    plain = new_pair(spec, tmp_path / "plain")
    mixed = new_pair(replace(spec, storage=Storage(shuffle_ref=True, shuffle_target=True,
                                                   swap_ref_baselines=(0, 3, 5))),
                     tmp_path / "mixed")
    calibrate_flat(plain.ref_ms, plain.target_ms, method="pwc,cfpt")
    calibrate_flat(mixed.ref_ms, mixed.target_ms, method="pwc,cfpt")
    for name in ("PWC_DATA", "CFPT_DATA"):
        a = out_phase(plain.target_ms, name)
        b = out_phase(mixed.target_ms, name)
        # compare row by row through (time, ant1, ant2), never by position
        ka = np.lexsort((plain.ant2, plain.ant1, plain.time))
        kb = np.lexsort((mixed.ant2, mixed.ant1, mixed.time))
        assert np.max(np.abs(wrap(a[ka] - b[kb]))) < 1e-5
    assert np.max(np.abs(wrap(out_phase(mixed.target_ms) - expected_pwc_phase(mixed)))) < 1e-5


def test_flags_nans_and_zero_amplitudes(new_pair):
    truth = new_pair(PairSpec(n_time=300, seed=6, troposphere=Troposphere(step_rad=0.08)))
    n_row = truth.time.size
    rng = np.random.default_rng(1)
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        data, flag = t.getcol("DATA"), t.getcol("FLAG")
        bad = rng.choice(n_row, 60, replace=False)
        flag[bad[:20], 0, 0] = True
        data[bad[20:40], 0, 1] = np.nan
        data[bad[40:], 0, :] = 0
        t.putcol("DATA", data)
        t.putcol("FLAG", flag)
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        tflag, trow = t.getcol("FLAG"), t.getcol("FLAG_ROW")
        tbad = rng.choice(n_row, 30, replace=False)
        tflag[tbad[:15], 0, 1] = True
        trow[tbad[15:]] = True
        t.putcol("FLAG", tflag)
        t.putcol("FLAG_ROW", trow)
    ref_flag_cells = np.zeros((n_row, 2), bool)
    ref_flag_cells[bad[:20], 0] = True
    ref_flag_cells[bad[20:40], 1] = True
    ref_flag_cells[bad[40:], :] = True
    before = {c: col(truth.target_ms, c) for c in ("DATA", "FLAG", "FLAG_ROW", "UVW", "TIME", "WEIGHT")}
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cwu")
    flag = col(truth.target_ms, "FLAG")[:, 0, :]
    expected_flag = before["FLAG"][:, 0, :] | before["FLAG_ROW"][:, None] | ref_flag_cells
    assert np.array_equal(flag, expected_flag)
    assert np.array_equal(col(truth.target_ms, "FLAG_HITOPS_BACKUP"), before["FLAG"])
    for c in ("DATA", "FLAG_ROW", "UVW", "TIME", "WEIGHT"):
        assert np.array_equal(col(truth.target_ms, c), before[c], equal_nan=True), c
    # the unflagged samples are still right: flagged samples do not break wrap counting
    good = ~flag
    pwc = out_phase(truth.target_ms)
    assert np.max(np.abs(wrap(pwc - expected_pwc_phase(truth))[good])) < 1e-5
    assert np.all(col(truth.target_ms, "PWC_DATA")[:, 0, :][ref_flag_cells] == 0)
    s = report["samples"]
    assert s["reference_invalid"] + s["target_invalid"] == int(expected_flag.sum())
    # a second run (--overwrite) is idempotent and keeps the first backup
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cwu", overwrite=True)
    assert np.array_equal(col(truth.target_ms, "FLAG")[:, 0, :], expected_flag)
    assert np.array_equal(col(truth.target_ms, "FLAG_HITOPS_BACKUP"), before["FLAG"])


def test_unmatched_rows_are_flagged_and_other_columns_untouched(new_pair):
    truth = new_pair(PairSpec(n_time=200, seed=7))
    # move the reference rows of one baseline for the second half of the track a day
    # later, so the target rows there have no counterpart
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        a1, a2, tm = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("TIME")
        drop = np.flatnonzero((a1 == 1) & (a2 == 2) & (tm > np.median(tm)))
        tm[drop] += 86400.0
        t.putcol("TIME", tm)
    with pt.table(str(truth.target_ms), ack=False) as t:
        names = [c for c in t.colnames() if c != "FLAG"]
        before = {c: t.getcol(c) for c in names if c != "FLAG_CATEGORY"}
    report = calibrate_flat(truth.ref_ms, truth.target_ms)
    flag = col(truth.target_ms, "FLAG")[:, 0, :]
    missing = (truth.ant1 == 1) & (truth.ant2 == 2) & (truth.time > np.median(truth.time))
    assert np.array_equal(flag, np.repeat(missing[:, None], 2, axis=1))
    assert report["rows"]["matched"] == truth.time.size - drop.size
    assert report["samples"]["no_reference_row"] == 2 * drop.size
    for c, value in before.items():
        assert np.array_equal(col(truth.target_ms, c), value), c


def test_antenna_map_pairs_differently_named_stations(new_pair):
    truth = new_pair(PairSpec(n_time=150, seed=8, ref_names=("AP", "JC", "PV", "GL"),
                              target_names=("AP", "SM", "PV", "GL")))
    # without the map SM is a station of the target band only: its baselines are left out
    report = calibrate_flat(truth.ref_ms, truth.target_ms)
    sm_rows = (truth.ant1 == 1) | (truth.ant2 == 1)
    assert np.all(col(truth.target_ms, "FLAG")[sm_rows])
    assert not np.any(col(truth.target_ms, "FLAG")[~sm_rows])
    assert report["samples"]["no_reference_row"] == 2 * int(sm_rows.sum())
    assert {"reference": None, "reference_antenna": None, "target": "SM",
            "target_antenna": 1} in report["stations"]
    calibrate_flat(truth.ref_ms, truth.target_ms, antenna_map="JC=SM", overwrite=True)
    assert np.max(np.abs(wrap(out_phase(truth.target_ms) - expected_pwc_phase(truth)))) < 1e-5


#: three scans with a fast drift (the two tests below write into their own copies)
THREE_SCANS = PairSpec(n_time=600, n_scans=3, seed=9, troposphere=Troposphere(drift_rad=0.08))


def test_scans_restart_wrap_counting(new_pair, shared_pair):
    truth = new_pair(THREE_SCANS)
    report = calibrate_flat(truth.ref_ms, truth.target_ms)
    pwc = out_phase(truth.target_ms)
    assert np.max(np.abs(wrap(pwc - expected_pwc_phase(truth)))) < 1e-5
    # the per-scan restart matters: counting through the scans would give another answer
    single_scan = shared_pair(replace(THREE_SCANS, n_scans=1))      # only its truth is read
    assert np.max(np.abs(wrap(expected_pwc_phase(single_scan) - expected_pwc_phase(truth)))) > 0.5
    assert report["rows"]["matched"] == truth.time.size


def test_reported_wrap_events_are_the_wraps_inside_scans(new_pair):
    # the count restarts in every scan; those resets are not wraps and must not be reported
    truth = new_pair(THREE_SCANS)
    ref_wrapped = wrap(truth.ref_phase_true)
    expected = {}
    pairs = sorted(set(zip(truth.ant1.tolist(), truth.ant2.tolist())))
    for p, q in pairs:
        sel = np.flatnonzero((truth.ant1 == p) & (truth.ant2 == q))
        sel = sel[np.argsort(truth.time[sel])]
        same_scan = np.diff(truth.scan[sel]) == 0
        steps = np.abs(np.diff(ref_wrapped[sel], axis=0)) > np.pi
        expected[(p, q)] = steps[same_scan].sum(axis=0)
    for chunk_rows in (2_000_000, 97):
        report = calibrate_flat(truth.ref_ms, truth.target_ms, overwrite=True, chunk_rows=chunk_rows)
        names = list(DEFAULT_NAMES)
        got = {}
        for entry in report["wraps"]:
            a, b = entry["baseline"].split("-")
            got.setdefault((names.index(a), names.index(b)), []).append(entry["wrap_events"])
        assert sum(expected[k].sum() for k in expected) > 20  # the test needs wraps to count
        for key, counts in got.items():
            assert counts == expected[key].tolist(), (chunk_rows, key)


def test_time_chunks_carry_the_wrap_count(new_pair):
    truth = new_pair(PairSpec(n_time=500, n_scans=2, seed=10,
                              troposphere=Troposphere(phase_offset_rad=1.0)))
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu",
              offset_reference_column="CORRECTED_DATA")
    whole = {c: col(truth.target_ms, c) for c in ("PWC_DATA", "CFPT_DATA", "CWU_DATA", "FLAG")}
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu", overwrite=True,
                       offset_reference_column="CORRECTED_DATA", chunk_rows=97)
    for c, value in whole.items():
        assert np.array_equal(col(truth.target_ms, c), value), c
    assert np.max(np.abs(wrap(out_phase(truth.target_ms) - truth.source_phase))) < 1e-5
    assert report["rows"]["target"] == truth.time.size


@pytest.mark.parametrize("order", ["baseline", "shuffled", "time"])
def test_chunked_run_reads_at_most_chunk_rows_at_once(new_pair, order, monkeypatch):
    """Memory is bounded by --chunk-rows: no read (metadata or data) of either band holds
    more rows than one chunk, on baseline-major, shuffled and time-ordered tables, and the
    output is the one-chunk output.  The reads are the real reads, counted (tests/read_spy.py)."""
    from read_spy import record_reads

    truth = new_pair(PairSpec(n_time=300, n_scans=2, seed=21,
                              troposphere=Troposphere(phase_offset_rad=1.0),
                              storage=Storage(shuffle_ref=order == "shuffled",
                                              shuffle_target=order == "shuffled",
                                              time_order=order == "time")))
    if order == "time":   # the layout the test means to exercise
        with pt.table(str(truth.target_ms), ack=False) as t:
            assert np.all(np.diff(t.getcol("TIME")) >= 0)
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase))
    kw = dict(method="pwc,cfpt", offset_reference_column="CORRECTED_DATA")
    with record_reads(monkeypatch) as whole_reads:
        whole_report = calibrate_flat(truth.ref_ms, truth.target_ms, **kw)
    whole = {c: col(truth.target_ms, c) for c in ("PWC_DATA", "CFPT_DATA", "FLAG")}
    chunk_rows = 120
    with record_reads(monkeypatch) as reads:
        report = calibrate_flat(truth.ref_ms, truth.target_ms, overwrite=True, chunk_rows=chunk_rows,
                           **kw)
    for c, value in whole.items():
        assert np.array_equal(col(truth.target_ms, c), value), c
    n_row = truth.time.size
    assert n_row > 10 * chunk_rows   # the track is far longer than one chunk
    # one-chunk run: whole-table reads; chunked run: none above 2 x chunk_rows (a chunk
    # holds <= 2 x chunk_rows rows of both bands together, and time blocks <= chunk_rows)
    assert max(n for _, _, n in whole_reads) == n_row
    assert {ms for ms, _, _ in reads} == {str(truth.ref_ms), str(truth.target_ms)}
    assert max(n for _, _, n in reads) <= 2 * chunk_rows
    # ... and every row of both bands was read (index pass + chunks)
    for ms in (str(truth.ref_ms), str(truth.target_ms)):
        assert sum(n for m, cols, n in reads if m == ms and "ANTENNA1" in cols) >= n_row
    assert report["chunks"] > 10 and whole_report["chunks"] == 1
    for key in ("rows", "samples", "wraps"):
        assert report[key] == whole_report[key], key
    # the same n0 per series (the residuals are sums in another order: equal to rounding)
    pick = [[(e["baseline"], e["correlation"], e["scan"], e["k"], e.get("samples"))
             for e in r["offset_step"]["series"]] for r in (report, whole_report)]
    assert pick[0] == pick[1]


def test_ref_model_column_removes_source_structure(new_pair):
    truth = new_pair(PairSpec(n_time=200, seed=12))
    # give the reference band a known source phase and a model column holding it
    structure = np.random.default_rng(3).uniform(-2, 2, truth.ref_phase_true.shape)
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        t.putcol("DATA", t.getcol("DATA") * np.exp(1j * structure[:, None, :]).astype(np.complex64))
    add_column(truth.ref_ms, "MODEL_DATA", 0.7 * np.exp(1j * structure))
    calibrate_flat(truth.ref_ms, truth.target_ms, ref_model_column="MODEL_DATA")
    assert np.max(np.abs(wrap(out_phase(truth.target_ms) - expected_pwc_phase(truth)))) < 1e-4


def test_report_and_log(tmp_path, new_pair, caplog):
    truth = new_pair(PairSpec(n_time=100, seed=13))
    with caplog.at_level("INFO", logger="hitops"):
        report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    text = caplog.text
    assert "R = 2.674418605" in text and "eps = 0.674418604" in text
    assert "matched 600 of 600 target rows" in text
    assert "wraps AP-SM: RR" in text and "0 of 1200 target samples (row x correlation) not calibrated" in text
    on_disk = json.loads((tmp_path / "target.ms.hitops-calibrate.json").read_text())
    assert on_disk["columns"] == {"pwc": "PWC_DATA", "cfpt": "CFPT_DATA"}
    assert on_disk["ratio"] == pytest.approx(230 / 86)
    assert len(on_disk["wraps"]) == 12 and report["samples"]["target"] == 1200


@pytest.mark.slow
def test_distributed_local_cluster_gives_identical_output(new_pair):
    from distributed import LocalCluster

    truth = new_pair(PairSpec(n_time=300, seed=14, n_scans=2))
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu")
    calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna", output_column="PWC_ANT")
    threads = {c: col(truth.target_ms, c)
               for c in ("PWC_DATA", "CFPT_DATA", "CWU_DATA", "FLAG", "PWC_ANT")}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        # the robust trackers run in the client, the transfer tasks on the cluster
        calibrate_flat(truth.ref_ms, truth.target_ms, tracker="antenna", output_column="PWC_ANT",
                  overwrite=True, scheduler=cluster.scheduler_address, chunk_rows=400)
        report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu",
                           overwrite=True, scheduler=cluster.scheduler_address, chunk_rows=400)
        # the kernel tasks went to the cluster, the table reads and writes did not (a
        # scheduler that unpickles dask-ms handles keeps the table open after the run)
        prefixes = set(cluster.scheduler.task_prefixes)
        assert "transfer_batch" in prefixes, prefixes
        assert prefixes <= {"transfer_batch", "finalize"}, prefixes
    for c, value in threads.items():
        assert np.array_equal(col(truth.target_ms, c), value), c
    assert report["rows"]["matched"] == truth.time.size


@pytest.mark.slow
def test_command_line_with_a_cluster_creates_new_columns_first(tmp_path, new_pair):
    """The command line in its own process, a cluster in this one, a target set without
    the output column: the scheduler and workers hold the table open from the reads,
    so the column must exist before they do (once, this run hung)."""
    import subprocess
    import sys
    from pathlib import Path

    from distributed import LocalCluster

    truth = new_pair(PairSpec(n_time=200, seed=31, n_scans=2))
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        flag[::9, 0, 0] = True
        t.putcol("FLAG", flag)
    threads_dir = tmp_path / "threads"
    threads_dir.mkdir()
    threads_ms = threads_dir / "target.ms"
    import shutil
    shutil.copytree(truth.target_ms, threads_ms)
    calibrate_flat(truth.ref_ms, threads_ms, method="pwc,cfpt")
    hitops = Path(sys.executable).with_name("hitops")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        proc = subprocess.run([str(hitops), "calibrate", str(truth.ref_ms), str(truth.target_ms),
                               "--method", "pwc,cfpt", "--scheduler", cluster.scheduler_address],
                              capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    assert "before sending work to the cluster" in proc.stderr
    # the scheduler ran in this process and unpickled dask-ms table handles from the run's
    # graph; casacore's table cache here may still hold the table with the column list of
    # before the commit, so what the run wrote is read back by a fresh process
    written = tmp_path / "written.npz"
    subprocess.run([sys.executable, "-c",
                    "import sys, numpy as np\n"
                    "from casacore import tables as pt\n"
                    "t = pt.table(sys.argv[1], ack=False)\n"
                    "np.savez(sys.argv[2], names=np.array(sorted(t.colnames())),\n"
                    "         **{c: t.getcol(c) for c in ('PWC_DATA', 'CFPT_DATA', 'FLAG')})\n",
                    str(truth.target_ms), str(written)], check=True, timeout=120)
    got = np.load(written)
    for c in ("PWC_DATA", "CFPT_DATA", "FLAG"):
        assert np.array_equal(got[c], col(threads_ms, c)), c
    # the same columns as the threaded run: this run adds no flag, so FLAG is unchanged
    # and, as in a threaded run, no backup is made
    with pt.table(str(threads_ms), ack=False) as u:
        assert list(got["names"]) == sorted(u.colnames())
    assert "FLAG_HITOPS_BACKUP" not in list(got["names"])
    assert np.array_equal(got["FLAG"], flag)


def test_cluster_run_that_fails_drops_the_columns_it_created(new_pair, monkeypatch):
    import hitops.io.read as msio
    from distributed import LocalCluster

    truth = new_pair(PairSpec(n_time=100, seed=32))
    before = {c: col(truth.target_ms, c) for c in ("DATA", "FLAG")}

    def failing(*args, **kwargs):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(msio, "write_main_columns", failing)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        with pytest.raises(OSError, match="simulated"):
            calibrate_flat(truth.ref_ms, truth.target_ms, scheduler=cluster.scheduler_address)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert "PWC_DATA" not in t.colnames() and "FLAG_HITOPS_BACKUP" not in t.colnames()
    for c, value in before.items():
        assert np.array_equal(col(truth.target_ms, c), value), c


def test_all_reference_flagged_flags_everything_without_failing(new_pair):
    truth = new_pair(PairSpec(n_time=50, seed=15))
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        t.putcol("FLAG", np.ones_like(t.getcol("FLAG")))
    add_column(truth.target_ms, "CORRECTED_DATA", np.exp(1j * truth.source_phase))
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt,cwu",
                       offset_reference_column="CORRECTED_DATA")
    assert col(truth.target_ms, "FLAG").all()
    assert not np.any(col(truth.target_ms, "PWC_DATA"))
    assert report["samples"]["reference_invalid"] == report["samples"]["target"]
    assert all(e["samples"] == 0 and e["k"] == 0 for e in report["offset_step"]["series"])


def test_one_sample_baseline_and_ratio_below_one(new_pair):
    truth = new_pair(PairSpec(n_time=60, seed=16, ratio=0.6))
    # baseline AP-SM keeps one sample in the reference band; its other rows move away
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        a1, a2, tm = t.getcol("ANTENNA1"), t.getcol("ANTENNA2"), t.getcol("TIME")
        move = np.flatnonzero((a1 == 0) & (a2 == 1) & (tm != tm.min()))
        tm[move] += 86400.0
        t.putcol("TIME", tm)
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cwu")
    assert report["r"] == 0 and report["eps"] == pytest.approx(0.6)
    flag = col(truth.target_ms, "FLAG")[:, 0, 0]
    one = (truth.ant1 == 0) & (truth.ant2 == 1)
    assert flag[one].sum() == one.sum() - 1
    good = ~col(truth.target_ms, "FLAG")[:, 0, :]
    assert np.max(np.abs(wrap(out_phase(truth.target_ms) - expected_pwc_phase(truth))[good])) < 1e-5


def _two_channel_copy(src, dest, channel_gain=(1.0, 0.5), flag_second=None):
    """A 2-channel copy of a 1-channel MS (same subtables; both channels carry DATA)."""
    with pt.table(str(src), ack=False) as t:
        cols = {c: t.getcol(c) for c in ("TIME", "ANTENNA1", "ANTENNA2", "UVW", "SCAN_NUMBER",
                                          "INTERVAL", "EXPOSURE", "TIME_CENTROID", "DATA")}
    n_row, _, n_corr = cols["DATA"].shape
    desc = pt.maketabdesc([
        pt.makearrcoldesc("DATA", 0j, shape=[2, n_corr], valuetype="complex", options=4),
        pt.makearrcoldesc("FLAG", False, shape=[2, n_corr], valuetype="boolean", options=4)])
    ms = pt.default_ms(str(dest), desc)
    ms.addrows(n_row)
    for c, v in cols.items():
        if c != "DATA":
            ms.putcol(c, v)
    data = np.concatenate([cols["DATA"] * g for g in channel_gain], axis=1).astype(np.complex64)
    flag = np.zeros((n_row, 2, n_corr), bool)
    if flag_second is not None:
        flag[flag_second, 1, :] = True
        data[flag_second, 1, :] = np.nan        # flagged channels must not leak in
    ms.putcol("DATA", data)
    ms.putcol("FLAG", flag)
    ms.close()
    for sub in ("ANTENNA", "SPECTRAL_WINDOW", "POLARIZATION", "DATA_DESCRIPTION", "FIELD",
                "FEED", "OBSERVATION"):
        with pt.table(f"{src}::{sub}", ack=False) as s, \
                pt.table(f"{dest}::{sub}", readonly=False, ack=False) as d:
            s.copyrows(d)
    with pt.table(f"{dest}::SPECTRAL_WINDOW", readonly=False, ack=False) as t:
        f = t.getcell("CHAN_FREQ", 0)[0]
        t.putcol("NUM_CHAN", np.array([2], np.int32))
        for c in ("CHAN_FREQ", "CHAN_WIDTH", "EFFECTIVE_BW", "RESOLUTION"):
            t.putcell(c, 0, np.array([f - 1e6, f + 1e6]) if c == "CHAN_FREQ" else np.array([2e6, 2e6]))
    return data, flag


def test_average_channels(tmp_path, shared_pair):
    # the pair is only read: its two-channel copies are calibrated
    truth = shared_pair(PairSpec(n_time=100, seed=17,
                                 troposphere=Troposphere(phase_offset_rad=1.3)))
    ref2, tgt2 = tmp_path / "ref2.ms", tmp_path / "tgt2.ms"
    _two_channel_copy(truth.ref_ms, ref2, flag_second=np.arange(0, 600, 7))
    data, flag = _two_channel_copy(truth.target_ms, tgt2, flag_second=np.arange(3, 600, 5))
    # (without --average-channels each channel gets its own ratio: tests/test_calibrate_wideband.py)
    calibrate_flat(ref2, tgt2, average_channels=True)
    out = col(tgt2, "PWC_DATA")
    assert out.shape == (600, 2, 2)
    expected = expected_pwc_phase(truth)
    ok = ~col(tgt2, "FLAG")
    assert np.array_equal(ok[:, 0, :], np.ones((600, 2), bool))
    assert np.array_equal(ok[:, 1, :], ~flag[:, 1, :])
    for ch in range(2):
        good = ok[:, ch, :]
        assert np.max(np.abs(wrap(np.angle(out[:, ch, :]) - expected)[good])) < 1e-5
        assert np.allclose(np.abs(out[:, ch, :])[good], np.abs(data[:, ch, :])[good], rtol=1e-5)


@pytest.mark.slow
def test_command_line_run(tmp_path, new_pair):
    import subprocess
    import sys
    from pathlib import Path

    truth = new_pair(PairSpec(n_time=80, seed=18, ref_names=("AP", "JC", "PV", "GL"),
                              target_names=("AP", "SM", "PV", "GL")))
    hitops = Path(sys.executable).with_name("hitops")
    proc = subprocess.run([str(hitops), "calibrate", str(truth.ref_ms), str(truth.target_ms),
                           "--method", "pwc", "--antenna-map", "JC=SM", "--output-column",
                           "FPT_PWC", "--report", str(tmp_path / "r.json")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "wrote FPT_PWC" in proc.stderr and "R = 2.674418605" in proc.stderr
    # every line is the log's: python-casacore's converter printed "Data type: 24,
    # SORT_COLUMNSnot handled" while dask-ms built the MS description of a new column
    assert "not handled" not in proc.stderr, proc.stderr
    assert np.max(np.abs(wrap(out_phase(truth.target_ms, "FPT_PWC") - expected_pwc_phase(truth)))) < 1e-5
    assert json.loads((tmp_path / "r.json").read_text())["columns"] == {"pwc": "FPT_PWC"}


def test_failure_while_writing_rolls_back(new_pair, monkeypatch):
    import hitops.io.read as msio

    truth = new_pair(PairSpec(n_time=120, seed=19))
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        flag = t.getcol("FLAG")
        flag[::7, 0, 1] = True
        t.putcol("FLAG", flag)
    with pt.table(str(truth.ref_ms), readonly=False, ack=False) as t:
        rflag = t.getcol("FLAG")
        rflag[::5, 0, 0] = True            # so that the run adds flags
        t.putcol("FLAG", rflag)
    before = {c: col(truth.target_ms, c) for c in ("FLAG", "DATA")}
    original = msio.write_main_columns
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise OSError("disk full (simulated)")
        return original(*args, **kwargs)

    monkeypatch.setattr(msio, "write_main_columns", failing)
    with pytest.raises(OSError, match="simulated"):
        calibrate_flat(truth.ref_ms, truth.target_ms, chunk_rows=150)
    with pt.table(str(truth.target_ms), ack=False) as t:
        names = t.colnames()
    assert "PWC_DATA" not in names and "FLAG_HITOPS_BACKUP" not in names
    for c, value in before.items():
        assert np.array_equal(col(truth.target_ms, c), value), c


def test_a_time_gap_inside_one_scan_restarts_the_count(new_pair, caplog):
    """SCAN_NUMBER says one scan (as after some UVFITS round trips), but no sample exists
    for two minutes: the count must restart after the gap, as it does at a new scan."""
    truth = new_pair(PairSpec(n_time=400, n_scans=2, seed=12,
                              troposphere=Troposphere(drift_rad=0.08, phase_offset_rad=1.0)))
    second = truth.scan == 2
    for ms in (truth.ref_ms, truth.target_ms):
        with pt.table(str(ms), readonly=False, ack=False) as t:
            scan, time = t.getcol("SCAN_NUMBER"), t.getcol("TIME")
            later = scan == 2
            t.putcol("TIME", np.where(later, time + 120.0, time))
            t.putcol("SCAN_NUMBER", np.ones_like(scan))
    truth.time[second] += 120.0
    with caplog.at_level("INFO", logger="hitops"):
        calibrate_flat(truth.ref_ms, truth.target_ms)
    assert "1 time gap(s) longer than" in caplog.text and "SCAN_NUMBER 1" in caplog.text
    # the truth of the two-scan pair: the count restarts after the gap
    assert np.max(np.abs(wrap(out_phase(truth.target_ms) - expected_pwc_phase(truth)))) < 1e-5


def test_cluster_rerun_with_overwrite_of_its_own_output(new_pair):
    """A column a cluster run created (through a staging column, renamed at the commit)
    keeps its data manager's name; a second cluster run with --overwrite stages the
    column again and must pick a data manager name that is free (it once collided)."""
    from distributed import LocalCluster

    truth = new_pair(PairSpec(n_time=100, seed=33))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", no_verdict=True,
                  scheduler=cluster.scheduler_address)
        first = col(truth.target_ms, "PWC_DATA")
        calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", no_verdict=True, overwrite=True,
                  scheduler=cluster.scheduler_address)
    np.testing.assert_array_equal(col(truth.target_ms, "PWC_DATA"), first)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert not [c for c in t.colnames() if c.startswith("HITOPS_PARTIAL_")]


def test_staging_columns_take_the_target_columns_storage(new_pair):
    """The outputs are stored like the column they copy: tiled like DATA with its tiles
    when the chunks are written in time order, short tiles and a bounded cache when
    they are scattered over a table not in time order; StandardStMan otherwise.  A
    TiledColumnStMan of fixed cell shape gives a TiledColumnStMan (cheap to add), any
    other tiled column a TiledShapeStMan."""
    from hitops.calibrate.output import (SCATTERED_CACHE_BYTES, SCATTERED_TILE_ROWS,
                                         like_dminfo)

    tiled = {"TYPE": "TiledColumnStMan", "SPEC": {"DEFAULTTILESHAPE": np.array([4, 1, 32768])}}
    seq = like_dminfo(tiled, "X", taken={"X_TSM"})
    assert seq["TYPE"] == "TiledShapeStMan" and seq["NAME"] == "X_TSM2"
    assert list(seq["SPEC"]["DEFAULTTILESHAPE"]) == [4, 1, 32768]
    fixed = like_dminfo(tiled, "X", taken={"X_TSM"}, fixed_shape=True)
    assert fixed["TYPE"] == "TiledColumnStMan" and fixed["NAME"] == "X_TCM"
    assert like_dminfo({"TYPE": "TiledShapeStMan", "SPEC": {"DEFAULTTILESHAPE": np.array(
        [4, 1, 32768])}}, "X", fixed_shape=True)["TYPE"] == "TiledShapeStMan"
    spread = like_dminfo(tiled, "X", scattered=True)
    assert list(spread["SPEC"]["DEFAULTTILESHAPE"]) == [4, 1, SCATTERED_TILE_ROWS]
    assert spread["SPEC"]["MAXIMUMCACHESIZE"] == SCATTERED_CACHE_BYTES
    assert like_dminfo({"TYPE": "StandardStMan"}, "X")["TYPE"] == "StandardStMan"
    # a baseline-major pair cut into chunks: the output is tiled with short tiles
    truth = new_pair(PairSpec(n_time=400, seed=5))
    report = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc", chunk_rows=500)
    assert report["chunks"] > 2
    with pt.table(str(truth.target_ms), ack=False) as t:
        info = next(v for v in t.getdminfo().values() if "PWC_DATA" in v["COLUMNS"])
        data_type = next(v["TYPE"] for v in t.getdminfo().values() if "DATA" in v["COLUMNS"])
    assert data_type == "TiledColumnStMan" and info["TYPE"] == "TiledColumnStMan"
    assert int(info["SPEC"]["DEFAULTTILESHAPE"][-1]) == SCATTERED_TILE_ROWS
