"""Parameter files written by the recipes themselves (issue 29).

Each recipe's first step (cab ``hitops.params``, ``hitops/recipe_params.py``)
writes ``{dir}/params/STEP.json`` for every other step, rewritten only when
the values it holds change; the steps list their file in ``depends``.  So a
changed parameter reruns the steps that use it, and what reads their outputs,
under plain ``stimela run`` as under ``python -m hitops.run``.

The slow tests run real Stimela (native backend) on
``tests/data/recipes/freshness.yml`` (hitops simulate -> calibrate ->
diagnose on a 3-station, 15-minute demo scene), reading which steps ran from
Stimela's own log lines and the outputs' modification times.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hitops.errors import InputError
from hitops.recipe_params import (PARAMS_CAB, UNSET_MARK, load_recipe, write_parameter_files,
                                  write_recipe_params)

ROOT = Path(__file__).resolve().parent.parent
RECIPES = ROOT / "recipes"
SMALL = ROOT / "tests" / "data" / "recipes" / "freshness.yml"
BIN = Path(sys.executable).parent


def _recipe_files():
    """Every recipe file under recipes/ (fpt-lib.yml holds only a sub-recipe)."""
    import yaml

    return sorted(p.name for p in RECIPES.glob("*.yml")
                  if any(isinstance(v, dict) and "steps" in v
                         for v in (yaml.safe_load(p.read_text()) or {}).values()))


SHIPPED = _recipe_files()


# ---------------------------------------------------------------------------
# the recipes and the tool, without Stimela

@pytest.mark.parametrize("recipe", SHIPPED + [str(SMALL)])
def test_every_recipe_starts_with_the_params_step_given_every_input(recipe):
    assert {"fpt-demo.yml", "fpt-paper.yml", "fpt-uvfits.yml"} <= set(SHIPPED)
    rec = load_recipe(RECIPES / recipe)
    first, sdef = next(iter(rec.steps.items()))
    assert sdef["cab"] == PARAMS_CAB, f"{recipe}: first step {first}"
    # it always runs: no skip, no skip_if_outputs, and kept by -s/-t selections
    assert "always" in sdef["tags"]
    assert "skip" not in sdef and "skip_if_outputs" not in sdef
    params = sdef["params"]
    assert params["recipe_file"] == "${self:path}" and params["outdir"] == "=recipe.dir"
    assert list(params["values"]) == list(rec.inputs)
    for name, formula in params["values"].items():
        schema = rec.inputs[name]
        optional = "default" not in schema and not schema.get("required")
        want = f'=IFSET(recipe.{name}, SELF, "{UNSET_MARK}")' if optional else f"=recipe.{name}"
        assert formula == want, f"{recipe}: {name}"
    # every step skipped while fresh lists its own parameter file
    for step, body in rec.steps.items():
        if body.get("skip_if_outputs") == "fresh":
            assert f"{{recipe.dir}}/params/{step}.json" in json.dumps(body["params"]["depends"]), \
                f"{recipe}: {step}"


def _values(rec, **changes):
    values = {k: s.get("default", UNSET_MARK) for k, s in rec.inputs.items()}
    values.update(changes)
    return values


def test_parameter_files_change_only_for_the_steps_that_use_a_value(tmp_path, capsys):
    rec = load_recipe(RECIPES / "fpt-demo.yml")

    def write(**changes):
        return write_recipe_params(str(rec.path), str(tmp_path), _values(rec, **changes))["changed"]

    assert write() == rec.parameter_steps()      # first run: every file but its own written
    # 14: the demo's steps after params, the run's page (report) last
    assert "params" not in rec.parameter_steps() and len(rec.parameter_steps()) == 14
    assert "parameters written for all 14 steps" in capsys.readouterr().out
    mtimes = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "params").iterdir()}
    assert write() == []                         # nothing changed: nothing rewritten
    assert mtimes == {p.name: p.stat().st_mtime_ns for p in (tmp_path / "params").iterdir()}
    assert write(fringefit_solint="60s") == ["fringefit"]
    assert capsys.readouterr().out.splitlines()[-1] == "parameters changed for: fringefit"
    assert write(fringefit_solint="60s", plots="coherence") == ["diagnose"]
    assert write(image_size=512) == ["images_table", "fringefit", "diagnose", "images"]  # back to defaults too
    assert write(seed=11) == ["simulate", "images_table", "images"]
    assert write(seed=11, threads=1, dir="elsewhere") == []   # these change no result
    stored = json.loads((tmp_path / "params" / "simulate.json").read_text())
    assert stored["inputs"]["seed"] == 11 and stored["inputs"]["scene"] == "demo"
    assert "dir" not in stored["inputs"]
    assert write() == ["simulate"]               # unset again
    assert json.loads((tmp_path / "params" / "simulate.json").read_text())["inputs"]["seed"] is None


def test_a_changed_step_definition_rewrites_only_that_steps_file(tmp_path):
    text = SMALL.read_text()
    recipe = tmp_path / "r.yml"
    recipe.write_text(text.replace("../../../cabs/", str(ROOT / "cabs") + "/"))
    rec = load_recipe(recipe)
    values = _values(rec)
    assert write_parameter_files(rec, values, tmp_path) == ["simulate", "calibrate", "diagnose"]
    recipe.write_text(recipe.read_text().replace("columns: DATA,PWC_DATA", "columns: PWC_DATA"))
    assert write_parameter_files(load_recipe(recipe), values, tmp_path) == ["diagnose"]
    # the step's info is a description, not a parameter
    recipe.write_text(recipe.read_text().replace("info: Coherence of", "info: The coherence of"))
    assert write_parameter_files(load_recipe(recipe), values, tmp_path) == []


def test_a_params_step_leaving_an_input_out_is_refused(tmp_path):
    rec = load_recipe(RECIPES / "fpt-demo.yml")
    values = _values(rec)
    del values["minsnr"]
    with pytest.raises(InputError, match=r"no value for minsnr"):
        write_recipe_params(str(rec.path), str(tmp_path), values)
    with pytest.raises(InputError, match=r"fringefit_soltint not an input"):
        write_recipe_params(str(rec.path), str(tmp_path),
                            _values(rec, fringefit_soltint="30s"))
    assert not (tmp_path / "params").exists()     # nothing written


def test_the_runner_refuses_a_dotted_name_stimela_would_drop():
    from hitops.run import UsageError, parse_overrides

    rec = load_recipe(RECIPES / "fpt-demo.yml")
    assert parse_overrides(rec, ["fringefit.minsnr=5", "log.level=INFO"]) == {
        "fringefit.minsnr": "5", "log.level": "INFO"}
    with pytest.raises(UsageError, match=r"'fringefitt' is not a step .* did you mean 'fringefit'"):
        parse_overrides(rec, ["fringefitt.minsnr=5"])
    with pytest.raises(UsageError, match=r"write 'diagnose.interval=...'"):
        parse_overrides(rec, ["steps.diagnose.params.interval=45"])


# ---------------------------------------------------------------------------
# real Stimela

def _env():
    env = dict(os.environ)
    # the python-flavour cabs run `python`, the binary ones `hitops`: both from the venv
    env["PATH"] = f"{BIN}:{env.get('PATH', '')}"
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".venv" / "numba-cache"))
    env["COLUMNS"] = "200"
    env["PYTHONPATH"] = str(ROOT)
    return env


def stimela_run(*args, cwd):
    done = subprocess.run([str(BIN / "stimela"), "-B", "run", str(SMALL), *args], cwd=cwd,
                          capture_output=True, text=True, env=_env(), timeout=600)
    assert done.returncode == 0, done.stdout[-5000:] + done.stderr[-2000:]
    return done.stdout


def ran_and_skipped(log: str):
    """(steps that ran, steps skipped as fresh), from Stimela's own lines."""
    ran, skipped, current = [], [], None
    for line in log.splitlines():
        start = re.search(r"STIMELA\.freshness INFO: processing step '([\w-]+)'", line)
        if start:
            current = start.group(1)
            ran.append(current)
        elif "STIMELA.freshness INFO: all required outputs are OK, skipping this step" in line:
            ran.remove(current)
            skipped.append(current)
    return ran, skipped


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("freshness")
    log = stimela_run("dir=out", cwd=work)
    assert ran_and_skipped(log) == (["params", "simulate", "calibrate", "diagnose"], [])
    return work


@pytest.fixture
def done_once(first_run, tmp_path):
    """A copy of the first run's directory (modification times kept)."""
    shutil.copytree(first_run / "out", tmp_path / "out")
    return tmp_path


def _mtime(path: Path) -> int:
    return path.stat().st_mtime_ns


@pytest.mark.slow
def test_plain_stimela_reruns_the_steps_a_changed_parameter_affects(done_once):
    work = done_once
    out = work / "out"
    summary, report = out / "diagnose" / "summary.json", out / "sim-230.ms.hitops-calibrate.json"
    params = {p.name: _mtime(p) for p in (out / "params").iterdir()}
    # nothing changed: only the parameter step runs, and rewrites nothing
    assert ran_and_skipped(stimela_run("dir=out", cwd=work)) == (
        ["params"], ["simulate", "calibrate", "diagnose"])
    assert params == {p.name: _mtime(p) for p in (out / "params").iterdir()}
    # a diagnose parameter: diagnose alone, and its table says so
    before = _mtime(report)
    assert ran_and_skipped(stimela_run("dir=out", "coherence_interval=30", cwd=work)) == (
        ["params", "diagnose"], ["simulate", "calibrate"])
    assert json.loads(summary.read_text())["interval_s"] == 30.0
    assert _mtime(report) == before
    # a calibrate parameter: calibrate, and diagnose because it reads calibrate's report
    sim, table = _mtime(out / "sim-86.ms"), _mtime(summary)
    assert ran_and_skipped(stimela_run("dir=out", "coherence_interval=30", "methods=pwc,cfpt",
                                       cwd=work)) == (["params", "calibrate", "diagnose"],
                                                      ["simulate"])
    assert _mtime(out / "sim-86.ms") == sim and _mtime(summary) > table
    assert "cfpt" in json.loads(report.read_text())["methods"]
    # a step selection keeps the parameter step (tagged always): the new interval reaches
    # diagnose's file, so diagnose reruns while calibrate, unchanged, is skipped
    log = stimela_run("dir=out", "coherence_interval=45", "methods=pwc,cfpt", "-s",
                      "calibrate:diagnose", cwd=work)
    assert ran_and_skipped(log) == (["params", "diagnose"], ["calibrate"])
    assert json.loads(summary.read_text())["interval_s"] == 45.0


def quiet_run(*args, cwd):
    done = subprocess.run([sys.executable, "-m", "hitops.run", str(SMALL), *args], cwd=cwd,
                          capture_output=True, text=True, env=_env(), timeout=600)
    statuses = dict(re.findall(r"^\[\d+/\d+\] (\S+) .* \.\. (.+)$", done.stdout, re.M))
    return done, statuses


@pytest.mark.slow
def test_the_quiet_runner_and_plain_stimela_share_the_parameter_files(done_once):
    work = done_once
    out = work / "out"
    done, statuses = quiet_run("dir=out", "coherence_interval=30", cwd=work)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    # the parameter step has no line of its own, only what changed
    assert list(statuses) == ["simulate", "calibrate", "diagnose"]
    assert statuses["simulate"] == statuses["calibrate"] == "up to date"
    assert re.fullmatch(r"[\d.]+ s", statuses["diagnose"]), statuses
    assert "parameters changed for: diagnose\n" in done.stdout
    assert json.loads((out / "diagnose" / "summary.json").read_text())["interval_s"] == 30.0
    # the same values through plain Stimela: the same files, nothing to rerun
    assert ran_and_skipped(stimela_run("dir=out", "coherence_interval=30", cwd=work)) == (
        ["params"], ["simulate", "calibrate", "diagnose"])
    # and back through the runner with nothing changed
    done, statuses = quiet_run("dir=out", "coherence_interval=30", cwd=work)
    assert done.returncode == 0 and set(statuses.values()) == {"up to date"}, done.stdout
    assert "parameters changed" not in done.stdout
    # the runner still refuses a misspelt name before anything runs
    done, _ = quiet_run("dir=out", "coherence_intervall=30", cwd=work)
    assert done.returncode == 2 and "did you mean 'coherence_interval'?" in done.stderr


@pytest.mark.slow
def test_plain_stimela_drops_a_misspelt_name_silently(done_once):
    """Stimela 2.1.4's own behaviour, documented in docs/recipes.md: an unknown
    name=value is assigned to the recipe, protected from assignment and so never
    reaches any step; the run succeeds as if it had not been given."""
    work = done_once
    log = stimela_run("dir=out", "coherence_intervall=30", cwd=work)
    assert ran_and_skipped(log) == (["params"], ["simulate", "calibrate", "diagnose"])
    assert "coherence_intervall" not in log
