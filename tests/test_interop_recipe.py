"""cabs/interop.yml and recipes/fpt-uvfits.yml: load through Stimela, match the code, run.

The run: a small UVFITS pair written by hitops (make_pair, exported) goes
through `stimela run recipes/fpt-uvfits.yml` (convert, calibrate with the
antenna tracker, diagnose, export); the exported UVFITS holds PWC_DATA, and a
second run skips every step.
"""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from test_cabs import CABS, IMAGE, load_cabs

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


def stimela(*args, cwd, timeout=600):
    env = dict(os.environ)
    env["PATH"] = f"{BIN}:{env.get('PATH', '')}"
    return subprocess.run([str(BIN / "stimela"), *args], cwd=cwd, capture_output=True,
                          text=True, env=env, timeout=timeout)


@pytest.fixture(scope="module")
def cabs():
    return load_cabs(CABS / "interop.yml")


def test_interop_cabs_load_and_pass_what_the_functions_take(cabs):
    from hitops.io.convert import convert_cab
    from hitops.io.uvfits import export_cab

    for name, func, file_output in (("hitops.convert", convert_cab, "ms"),
                                    ("hitops.export-uvfits", export_cab, "uvfits")):
        cab = cabs[name]
        assert cab["image"] == IMAGE and cab["flavour"] == "python"
        assert cab["command"] == f"{func.__module__}.{func.__name__}"
        signature = inspect.signature(func).parameters
        passed = [k for k, v in cab["inputs"].items() if not v["skip"]] + [file_output]
        assert sorted(passed) == sorted(signature), name
        for k, v in cab["inputs"].items():
            if k in signature and signature[k].default is not inspect.Parameter.empty:
                assert v["default"] == signature[k].default, f"{name}.{k}"
    # the generated calibrate cab has the new inputs (from the schema)
    assert {"workdir", "export_uvfits"} <= set(cabs["hitops.calibrate"]["inputs"])


def test_recipe_loads_and_validates(tmp_path):
    done = stimela("doc", str(ROOT / "recipes" / "fpt-uvfits.yml"), cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    for step in ("convert-ref", "convert-target", "calibrate", "diagnose", "export"):
        assert step in done.stdout


@pytest.mark.slow
def test_recipe_runs_on_a_uvfits_pair_and_reruns_as_skips(tmp_path, shared_pair):
    from casacore import tables as pt

    from hitops.io.fits import read_headers
    from hitops.io.uvfits import export_uvfits
    from hitops.testing import PairSpec, Troposphere

    # only read: the recipe runs on its UVFITS export
    truth = shared_pair(PairSpec(n_ant=4, n_time=300, dt=2.0, seed=3,
                                 troposphere=Troposphere(ref_offset_scale=0.0)))
    export_uvfits(truth.ref_ms, tmp_path / "ref.uvfits", "DATA")
    export_uvfits(truth.target_ms, tmp_path / "tgt.uvfits", "DATA")
    before = {p: (tmp_path / p).read_bytes() for p in ("ref.uvfits", "tgt.uvfits")}
    args = ("run", str(ROOT / "recipes" / "fpt-uvfits.yml"), "ref=ref.uvfits",
            "target=tgt.uvfits", "dir=out")
    done = stimela(*args, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-5000:] + done.stderr[-3000:]
    out = tmp_path / "out"
    report = json.loads((out / "target.ms.hitops-calibrate.json").read_text())
    assert report["tracker"] == "antenna"
    summary = json.loads((out / "diagnose" / "summary.json").read_text())
    for bl in summary["baselines"]:
        assert bl["columns"]["PWC_DATA"]["coherence_factor"] > 0.999
    headers = read_headers(out / "target-pwc.uvfits")
    assert headers[0][0]["GCOUNT"] == truth.time.size
    header_bytes = (out / "target-pwc.uvfits").read_bytes()[:headers[0][1]]
    assert b"visibilities from column PWC_DATA" in header_bytes
    with pt.table(str(out / "target.ms"), ack=False) as t:
        assert "PWC_DATA" in t.colnames()
    assert before == {p: (tmp_path / p).read_bytes() for p in before}   # inputs only read
    again = stimela(*args, cwd=tmp_path)
    assert again.returncode == 0, again.stdout[-3000:]
    assert again.stdout.count("skipping this step") == 5
