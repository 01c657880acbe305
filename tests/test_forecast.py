"""hitops forecast: slip model, outputs, bad input, and agreement with a direct simulation."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest

from hitops.errors import HitopsError
from hitops.forecast import forecast
from hitops.forecast import model
from hitops.forecast.validate import direct_check
from hitops.tracking import theory


@pytest.mark.parametrize("rho,sigma", [(1.5, 0.0), (2.0, 0.0), (3.0, 0.0), (2.5, 0.3), (1.0, 0.8)])
def test_tabulated_failure_probability_is_the_exact_theory(rho, sigma):
    exact = (theory.itoh_failure_probability_turbulent(rho, sigma) if sigma
             else theory.itoh_failure_probability(rho))
    assert model.naive_failure_probability(rho, sigma) == pytest.approx(exact, rel=0.02)


def test_forecast_paper_stations_writes_table_markdown_and_heatmap(tmp_path):
    payload = forecast(stations="paper", months="4", outdir=str(tmp_path), flux=0.05,
                       elevation=20.0)
    with open(tmp_path / "forecast.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 28 and {r["month"] for r in rows} == {"4"}
    assert all(int(r["n_samples"]) >= 56 for r in rows)
    assert (tmp_path / "forecast-heatmap.png").stat().st_size > 10_000
    assert "| PV-PB | Apr |" in (tmp_path / "forecast.md").read_text()
    p = {r["baseline"]: float(r["naive_p_hour_mean"]) for r in rows}
    assert p["KC-KY"] > p["PV-PB"]              # sea-level KVN at 0.05 Jy vs the big dishes
    for r in rows:                               # smoothing never does worse than counting
        assert float(r["smooth_p_hour_mean_bound"]) <= float(r["naive_p_hour_mean"]) + 1e-12
    assert set(payload["stations"]["AP"]) == {"4"}


@pytest.mark.parametrize("kwargs,words", [
    # every month is tabulated for the eight paper sites; LMT has only its April 2018 analyses
    (dict(stations="AP,LM", months="8"), ["station LM", "LMT", "month 8", "months with data there: 4"]),
    (dict(stations="AP,QQ"), ["unknown merra2 site 'QQ'", "nearest"]),
    (dict(stations="AP"), ["at least two stations"]),
    (dict(months="13"), ["1-12"]),
    (dict(elevation=0.0), ["elevation"]),
])
def test_bad_input_names_the_value_and_writes_nothing(tmp_path, kwargs, words):
    args = dict(stations="AP,PV", outdir=str(tmp_path / "out"))
    args.update(kwargs)
    with pytest.raises(HitopsError) as err:
        forecast(**args)
    for word in words:
        assert word in str(err.value)
    assert not (tmp_path / "out").exists()


def test_cli_forecast_and_existing_outputs(tmp_path):
    cmd = [sys.executable, "-m", "hitops.cli", "forecast", "--stations", "AP,PV,PB",
           "--outdir", str(tmp_path), "--no-plot"]
    assert subprocess.run(cmd, capture_output=True, text=True).returncode == 0
    again = subprocess.run(cmd, capture_output=True, text=True)
    assert again.returncode == 2 and "--overwrite" in again.stderr + again.stdout


@pytest.mark.parametrize("codes,start", [(("PV", "PB"), "2018-04-10T00:00:00"),
                                         (("AP", "GL"), "2018-04-10T02:00:00"),
                                         (("KP", "SM"), "2018-04-10T06:00:00")])
def test_slip_model_agrees_with_simulate_and_calibrate(tmp_path, codes, start):
    """hitops simulate (MERRA-2 weather of 2018-04-10) + hitops calibrate --tracker count:
    the failures of naive counting match the model's prediction within 3 Poisson sigma."""
    result = direct_check(list(codes), tmp_path, start=start, target_rho=2.0)
    assert result["predicted_failures"] > 10
    assert abs(result["z"]) < 3, result
