"""Every cab file loads through Stimela itself and agrees with the code it runs.

Stimela keeps its configuration in a process-wide object, so loading happens
in a subprocess (the same code path as `stimela doc` / `stimela run`).
"""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CABS = ROOT / "cabs"
IMAGE = "ghcr.io/hitops/hitops:0.1.0"

_LOADER = r"""
import json, sys
import stimela
from stimela import config
stimela.VERBOSE = 0
stimela.CONFIG = config.load_config(extra_configs=[])
from stimela.commands.run import load_recipe_files
from stimela.kitchen.cab import Cab
from stimela.backends import resolve_image_name, StimelaBackendOptions
load_recipe_files(sys.argv[1:])
out = {}
for name, conf in stimela.CONFIG.cabs.items():
    cab = Cab(**conf)
    cab.finalize(config=stimela.CONFIG)
    flavour = cab.flavour
    out[name] = {
        "command": cab.command,
        "flavour": getattr(flavour, "kind", None),
        "interpreter": getattr(flavour, "interpreter_binary", None),
        "image": resolve_image_name(StimelaBackendOptions(), cab.image) if cab.image else None,
        "inputs": {k: {"dtype": str(v.dtype), "skip": bool((v.policies and v.policies.skip)),
                       "implicit": v.implicit, "default": v.default if not hasattr(v.default, "__dict__") else None,
                       "skip_freshness_checks": bool(v.skip_freshness_checks)}
                   for k, v in cab.inputs.items()},
        "outputs": {k: {"dtype": str(v.dtype), "implicit": v.implicit} for k, v in cab.outputs.items()},
    }
print("CABS-JSON:" + json.dumps(out, default=str))
"""


def load_cabs(*files, cwd=None):
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    # never the repository: Stimela would leave its logs in the working directory
    done = subprocess.run([sys.executable, "-c", _LOADER, *map(str, files)], cwd=cwd or tempfile.gettempdir(),
                          capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    line = next(l for l in done.stdout.splitlines() if l.startswith("CABS-JSON:"))
    return json.loads(line[len("CABS-JSON:"):])


@pytest.fixture(scope="module")
def cabs():
    return load_cabs(CABS / "hitops-pipeline.yml", CABS / "casa.yml", CABS / "wsclean.yml")


EXPECTED = ["hitops.simulate", "hitops.calibrate", "hitops.diagnose", "hitops.compare",
            "hitops.casa.fringefit", "hitops.casa.gaincal", "hitops.casa.applycal",
            "hitops.casa.imfit", "hitops.wsclean"]


def test_every_cab_loads_and_names_the_hitops_image(cabs):
    for name in EXPECTED:
        assert name in cabs, f"cab {name} missing"
        assert cabs[name]["image"] == IMAGE, f"{name} runs in {cabs[name]['image']}"


def test_casa_cabs_run_natively_with_the_plain_python(cabs):
    # cult-cargo's casa cabs call python3.10, which does not exist here
    for name in ("fringefit", "gaincal", "applycal", "imfit"):
        cab = cabs[f"hitops.casa.{name}"]
        assert cab["flavour"] == "python" and cab["interpreter"] == "python"
        assert cab["command"] == f"hitops.casa.tasks.{name}"


def test_python_cabs_pass_only_parameters_the_function_accepts(cabs):
    import hitops.casa.tasks as tasks

    for name in ("fringefit", "gaincal", "applycal", "imfit"):
        cab = cabs[f"hitops.casa.{name}"]
        signature = inspect.signature(getattr(tasks, name)).parameters
        passed = [k for k, v in cab["inputs"].items() if not v["skip"]]
        named_outputs = [k for k, v in cab["outputs"].items()
                         if not v["implicit"] and v["dtype"] in ("<class 'scabha.basetypes.File'>",
                                                                  "<class 'scabha.basetypes.Directory'>")
                         or k in ("caltable", "receipt", "outfile")]
        for param in passed + named_outputs:
            assert param in signature, f"hitops.casa.{name}: cab passes '{param}', " \
                                       f"tasks.{name} does not accept it"
        # every required function argument is provided by the cab
        for param, spec in signature.items():
            if spec.default is inspect.Parameter.empty:
                assert param in passed + named_outputs, f"{name}: '{param}' never passed"


def test_casa_defaults_follow_the_paper(cabs):
    assert cabs["hitops.casa.fringefit"]["inputs"]["solint"]["default"] == "20s"
    assert cabs["hitops.casa.gaincal"]["inputs"]["solint"]["default"] == "10s"
    assert cabs["hitops.casa.gaincal"]["inputs"]["calmode"]["default"] == "p"


def test_in_place_measurement_sets_are_left_out_of_freshness_checks(cabs):
    # the 230 GHz MS is changed in place by applycal and hitops calibrate; steps
    # use `depends` (never passed to the tool) for their freshness instead
    for name in ("hitops.casa.fringefit", "hitops.casa.gaincal", "hitops.casa.applycal"):
        assert cabs[name]["inputs"]["vis"]["skip_freshness_checks"]
        assert cabs[name]["inputs"]["depends"]["skip"]
    assert cabs["hitops.wsclean"]["inputs"]["ms"]["skip_freshness_checks"]
    for name in ("hitops.calibrate", "hitops.diagnose", "hitops.compare"):
        assert cabs[name]["inputs"]["depends"]["skip"]
    # calibrate declares no outputs; the pipeline adds its report so skipping works
    assert cabs["hitops.calibrate"]["outputs"]["report_file"]["implicit"] == \
        "{current.target_ms}.hitops-calibrate.json"


def test_wsclean_cab_outputs_and_units(cabs):
    ws = cabs["hitops.wsclean"]
    assert ws["outputs"]["restored"]["implicit"] == "{current.name}-image.fits"
    assert ws["outputs"]["dirty"]["implicit"] == "{current.name}-dirty.fits"
    # WSClean 3.1 takes asec/masec, not uas
    assert ws["inputs"]["scale"]["default"].endswith("masec")


def test_generated_hitops_cabs_are_current():
    from hitops.cabgen import render

    assert (CABS / "hitops.yml").read_text() == render(), \
        "cabs/hitops.yml is out of date: run `python -m hitops.cabgen`"


def test_stimela_doc_accepts_every_cab_file(tmp_path):
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}:{env.get('PATH', '')}"
    for path in ("casa.yml", "wsclean.yml", "hitops-pipeline.yml"):
        # in a scratch directory: `stimela doc` writes log-stimela.txt where it runs
        done = subprocess.run([str(Path(sys.executable).parent / "stimela"), "doc",
                               str(CABS / path)], cwd=tmp_path, capture_output=True, text=True,
                              env=env, timeout=120)
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]


def test_a_broken_cab_fails_to_load(tmp_path):
    bad = tmp_path / "bad.yml"
    bad.write_text("cabs:\n  bad:\n    command: x\n    inputs:\n      a: {dtype: NoSuchType}\n")
    env = dict(os.environ)
    done = subprocess.run([sys.executable, "-c", _LOADER, str(bad)], cwd=tmp_path,
                          capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode != 0
