"""hitops diagnose on wideband sets: coherence per channel, per window and across all channels,
the waterfall and spectrum plots (truth: the simulator's excess path and analytic sums)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest
from casacore import tables as pt

from hitops.diagnose import diagnose
from hitops.diagnose.read import read_grid
from hitops.diagnose.spectral_read import band_average, is_spectral, read_spectral
from hitops.simulate import simulate
from test_simulate import small_scene  # tests/ is on sys.path (rootdir-relative)

C = 299792458.0
TAU = 0.2e-9                   # residual delay of DELAY_DATA (s)


def _scene() -> dict:
    scene = small_scene(bands=[
        {"name": "86", "freq_ghz": 86, "bandwidth_ghz": 2, "n_chan": 16},
        {"name": "230", "freq_ghz": 228.1, "bandwidth_ghz": 2, "n_chan": 16,
         "windows_ghz": [227.1, 229.1]}])
    scene["corruptions"].update({"noise": False, "coherence_scale": 0.5})
    return scene


def _add_column(table, name: str, values: np.ndarray) -> None:
    dm = dict(table.getdminfo("DATA"), NAME=f"{name}_dm")
    table.addcols(pt.makecoldesc(name, table.getcoldesc("DATA")), dm)
    table.putcol(name, values.astype(np.complex64))


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    """The 230 GHz set with three corrections written from the truth's excess path:
    TRUE_DATA per channel (exact), WINDOW_DATA one ratio per window, DELAY_DATA exact
    plus a constant residual delay."""
    out = tmp_path_factory.mktemp("diag-wide")
    paths = simulate(_scene(), out, save_truth=True)
    truth = np.load(paths["truth"])
    ms = str(paths["230"])
    with pt.table(ms, readonly=False, ack=False) as t:
        data, ddid, time, a1, a2 = (t.getcol(c) for c in ("DATA", "DATA_DESC_ID", "TIME",
                                                          "ANTENNA1", "ANTENNA2"))
        with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as spw:
            freq = spw.getcol("CHAN_FREQ")[ddid]
        ti = np.searchsorted(truth["time"], time)
        d_path = truth["path_m"][a1, ti] - truth["path_m"][a2, ti]
        true = data * np.exp(-2j * np.pi * freq * d_path[:, None] / C)[:, :, None]
        centre = freq.mean(axis=1, keepdims=True)
        _add_column(t, "TRUE_DATA", true)
        _add_column(t, "WINDOW_DATA",
                    data * np.exp(-2j * np.pi * centre * d_path[:, None] / C)[:, :, None])
        _add_column(t, "DELAY_DATA",
                    true * np.exp(2j * np.pi * (freq - centre) * TAU)[:, :, None])
    return paths, out


def test_coherence_per_channel_window_and_all(wide):
    paths, out = wide
    summary = diagnose(paths["230"], columns="DATA,TRUE_DATA,WINDOW_DATA,DELAY_DATA",
                       interval=600, outdir=out / "diag", plots="waterfall,spectrum")
    spectral = summary["spectral"]
    assert [w["spw"] for w in spectral["windows"]] == [0, 1]
    assert [w["n_chan"] for w in spectral["windows"]] == [16, 16]
    cols = spectral["columns"]
    # exact per-channel correction: every channel and window coherent
    assert cols["TRUE_DATA"]["min_channel"] > 0.99999
    assert cols["TRUE_DATA"]["median_all_channels"] > 0.99999
    # a constant delay: each channel stays coherent, the window loses
    # |sum_k exp(2 pi i (nu_k - nu_c) tau)| / n = |sin(pi n d tau) / (n sin(pi d tau))|
    n, d = 16, 125e6
    analytic = abs(np.sin(np.pi * n * d * TAU) / (n * np.sin(np.pi * d * TAU)))
    assert cols["DELAY_DATA"]["min_channel"] > 0.99999
    for name, entry in cols["DELAY_DATA"]["baselines"].items():
        assert entry["windows"] == pytest.approx([analytic, analytic], abs=1e-4), name
        assert entry["all_channels"] == pytest.approx(analytic, abs=1e-4)
    # one ratio per window: channels drift apart; the edge channels lose most
    for name, entry in cols["WINDOW_DATA"]["baselines"].items():
        chans = np.array(entry["channels"][0])
        assert chans[[0, -1]].min() < chans[7:9].min() + 1e-9, name
    assert cols["WINDOW_DATA"]["median_all_channels"] < 0.999
    assert cols["DATA"]["median_all_channels"] < 0.5
    # the files
    rows = list(csv.DictReader(open(out / "diag" / "spectral-table.csv")))
    assert len(rows) == 4 * 10 * 3              # columns x baselines x (2 windows + all)
    assert {r["window"] for r in rows} == {"0", "1", "all"}
    saved = json.loads((out / "diag" / "summary.json").read_text())
    assert saved["spectral"]["columns"]["DELAY_DATA"]["median_windows"][0] == pytest.approx(
        analytic, abs=1e-4)
    text = (out / "diag" / "coherence-table.txt").read_text()
    assert "Wideband coherence at T = 600 s (2 window(s))" in text
    plots = summary["outputs"]["plots"]
    assert sum("waterfall-" in p for p in plots) == 10
    assert any(p.endswith("coherence-spectrum.png") for p in plots)


def test_waterfall_shows_flat_channels_flat(wide):
    """The waterfall's cells: TRUE_DATA constant along time in every channel, DATA not."""
    from hitops.diagnose.spectral import spectral_coherence
    from hitops.diagnose.spectral_plots import waterfall_figure

    paths, _ = wide
    grid = read_spectral(str(paths["230"]), ["DATA", "TRUE_DATA", "DELAY_DATA"],
                         baselines="PV-PB")
    res = spectral_coherence(grid, 600, 0.5)
    fig = waterfall_figure(grid, 0, ["DATA", "TRUE_DATA", "DELAY_DATA"], res)
    waterfalls = [ax for ax in fig.axes if ax.get_ylabel() == "frequency (GHz)"]
    assert len(waterfalls) == 3
    for ax, flat in zip(waterfalls, (False, True, True)):
        for mesh in ax.collections[:2]:                        # the two windows
            phase = np.asarray(mesh.get_array()).reshape(16, -1)   # (channel, time bin)
            spread = np.nanmax(np.ptp(phase, axis=1))
            assert (spread < 1e-4) if flat else (spread > 1.0)
    # the delay shows along frequency: channel phases differ by 2 pi d tau
    phase = np.asarray(waterfalls[2].collections[0].get_array()).reshape(16, -1)[:, 0]
    np.testing.assert_allclose(np.diff(phase), 2 * np.pi * 125e6 * TAU, atol=1e-5)


def test_band_average_of_one_window_equals_the_single_window_reader(wide):
    """86 GHz: one window of 16 channels; both readers give the same averaged samples."""
    paths, _ = wide
    ms = str(paths["86"])
    assert is_spectral(ms)
    old = read_grid(ms, ["DATA"])
    new = band_average(read_spectral(ms, ["DATA"]))
    np.testing.assert_array_equal(old.ant1, new.ant1)
    np.testing.assert_array_equal(old.times, new.times)
    np.testing.assert_allclose(new.vis_stack, old.vis_stack, atol=1e-6)
    np.testing.assert_array_equal(new.flag, old.flag)


def test_flagged_channels_are_left_out(wide, tmp_path):
    """Half of window 1's channels flagged: they have no coherence, the rest is unchanged."""
    paths, _ = wide
    ms = tmp_path / "flagged.ms"
    with pt.table(str(paths["230"]), ack=False) as t:
        t.copy(str(ms), deep=True).close()
    with pt.table(str(ms), readonly=False, ack=False) as t:
        flag, ddid = t.getcol("FLAG"), t.getcol("DATA_DESC_ID")
        flag[ddid == 1, :8] = True
        t.putcol("FLAG", flag)
    summary = diagnose(ms, columns="TRUE_DATA,DELAY_DATA", interval=600, outdir=None)
    entry = summary["spectral"]["columns"]["DELAY_DATA"]["baselines"]["AP-PV"]
    assert entry["channels"][1][:8] == [None] * 8
    n, d = 8, 125e6
    # the 8 unflagged channels sit at offsets 0.5..7.5 channels above the centre: a phase
    # ramp whose vector mean is |sin(pi n d tau) / (n sin(pi d tau))| again
    assert entry["windows"][1] == pytest.approx(
        abs(np.sin(np.pi * n * d * TAU) / (n * np.sin(np.pi * d * TAU))), abs=1e-4)


def test_single_channel_set_gets_no_spectral_section(tmp_path):
    paths = simulate("demo", tmp_path, duration=600, no_noise=True)
    assert not is_spectral(str(paths["230"]))
    summary = diagnose(paths["230"], columns="DATA", interval=60, outdir=tmp_path / "d",
                       plots="waterfall")
    assert summary["spectral"] is None
    assert any("no waterfall" in w for w in summary["warnings"])


def test_cli_waterfall_and_spectrum(wide, tmp_path):
    paths, _ = wide
    proc = subprocess.run([sys.executable, "-m", "hitops.cli", "diagnose", str(paths["230"]),
                           "--columns", "DATA,TRUE_DATA", "--interval", "300", "--plots",
                           "waterfall,spectrum", "--baselines", "AP-PV", "--outdir",
                           str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "plots" / "waterfall-AP-PV.png").stat().st_size > 10_000
    assert (tmp_path / "plots" / "coherence-spectrum.png").exists()
    assert (tmp_path / "spectral-table.csv").exists()


def test_wideband_reference_wraps_are_those_of_the_band_centre(wide, tmp_path):
    """A 16-channel 86 GHz --ref-ms: the vector average of symmetric channels has exactly the
    phase at the window centre (2 pi nu_c dL / c), so its wraps are that phase's wraps."""
    from hitops.tracking.count import count_wraps

    paths, _ = wide
    summary = diagnose(paths["230"], columns="TRUE_DATA", interval=60, outdir=None,
                       ref_ms=paths["86"], baselines="PV-PB")
    truth = np.load(paths["truth"])
    codes = list(truth["stations"])
    d_path = truth["path_m"][codes.index("PV")] - truth["path_m"][codes.index("PB")]
    phase = np.angle(np.exp(2j * np.pi * 86e9 * d_path / C))
    count = count_wraps(np.ascontiguousarray(phase), np.ones(phase.size, bool))
    expected = int(np.count_nonzero(np.diff(count)))
    assert expected > 5
    assert summary["reference_wraps"]["PV-PB"] == {"RR": expected, "LL": expected}


def test_waterfall_bins_keep_scan_gaps_blank():
    """Two 10-sample scans 20 samples apart: the gap's bins are empty (NaN), the scans' are not."""
    from hitops.diagnose.spectral_plots import _binned, time_bins

    times = np.concatenate([np.arange(10), np.arange(30, 40)]) * 2.0 + 5e9
    bins, n_bin, factor = time_bins(times, 2.0)
    assert (n_bin, factor) == (40, 1)
    cube = np.exp(1j * np.linspace(0, 1, times.size))[:, None] * np.ones((1, 3))
    phase = _binned(cube, np.ones(cube.shape, bool), bins, n_bin)
    assert np.isnan(phase[10:30]).all() and np.isfinite(phase[:10]).all()
    np.testing.assert_allclose(phase[30:, 0], np.linspace(0, 1, 20)[10:])
