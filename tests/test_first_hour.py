"""A new user's first hour (issue 17), checked as that user would meet it.

* ``python -m hitops.run`` (what ``make run`` calls) refuses a misspelt or
  mistyped parameter before anything runs, naming the closest valid one;
* each step lists its parameter file (which the recipe's first step
  rewrites only when a value that step uses changes: tests/test_recipe_params.py),
  so only that step and what follows from it rerun;
* in a fresh clone with its own HOME and TMPDIR, the demo prints at most ~50
  lines ending with the table and the paths, leaves nothing outside ``out/``
  (nor in TMPDIR), reruns nothing when nothing changed, and reruns exactly
  the affected steps when a parameter changes;
* two environments on one machine each keep their own CASA configuration, and
  deleting one leaves the other working.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RECIPES = ROOT / "recipes"
BIN = Path(sys.executable).parent
DEMO_STEPS = ["simulate", "fringefit", "gaincal", "applycal", "calibrate", "diagnose",
              "images", "compare"]


def runner(*args, cwd, env=None, timeout=900):
    env = dict(env or os.environ)
    env["PATH"] = f"{BIN}:{env.get('PATH', '')}"
    return subprocess.run([sys.executable, "-m", "hitops.run", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, env=env, timeout=timeout)


# ---------------------------------------------------------------------------
# parameters: checked, and part of what decides freshness (no Stimela run)

def test_a_misspelt_parameter_fails_naming_the_closest(tmp_path):
    out = tmp_path / "demo"
    done = runner(RECIPES / "fpt-demo.yml", f"dir={out}", "fringefit_soltint=30s", cwd=tmp_path)
    assert done.returncode == 2
    assert "unknown parameter 'fringefit_soltint'" in done.stderr
    assert "did you mean 'fringefit_solint'?" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not out.exists()   # refused before anything was written
    done = runner(RECIPES / "fpt-demo.yml", f"dir={out}", "seed=eleven", cwd=tmp_path)
    assert done.returncode == 2 and "seed='eleven': an integer is needed" in done.stderr
    done = runner(RECIPES / "fpt-paper.yml", f"dir={out}", "max_offset_wrap=40", cwd=tmp_path)
    assert done.returncode == 2 and "did you mean 'max_offset_wraps'?" in done.stderr


@pytest.mark.parametrize("recipe", ["fpt-demo.yml", "fpt-paper.yml"])
def test_every_fresh_checked_step_depends_on_its_parameter_file(recipe):
    import yaml

    from hitops.run import load_recipe

    rec = load_recipe(RECIPES / recipe)
    for step in DEMO_STEPS:
        sdef = rec.steps[step]
        text = yaml.safe_dump(sdef.get("params", {}).get("depends", []))
        assert f"{{recipe.dir}}/params/{step}.json" in text, f"{recipe}: {step}"
        if step != "images":   # a sub-recipe: its steps carry skip_if_outputs
            assert sdef.get("skip_if_outputs") == "fresh", f"{recipe}: {step}"
    # and so does any other step that is skipped when fresh
    for step, sdef in rec.steps.items():
        if sdef.get("skip_if_outputs") == "fresh":
            text = yaml.safe_dump(sdef.get("params", {}).get("depends", []))
            assert f"{{recipe.dir}}/params/{step}.json" in text, f"{recipe}: {step}"
    # nothing is skipped merely because a set exists (the old simulate rule)
    assert "skip" not in rec.steps["simulate"]
    # the sub-recipe passes `depends` on to the WSClean step
    lib = rec.libs["image-fit"]
    assert lib["steps"]["image"]["params"]["depends"] == "=recipe.depends"
    assert lib["steps"]["image"]["skip_if_outputs"] == "fresh"


# ---------------------------------------------------------------------------
# the demo in a fresh clone, as a new user runs it

def _tree(root: Path):
    return {str(p.relative_to(root)) for p in root.rglob("*")
            if ".git" not in p.relative_to(root).parts}


def _statuses(stdout: str):
    """step -> what its progress line ended with ('up to date', '3.1 s', ...)."""
    out = {}
    for line in stdout.splitlines():
        match = re.match(r"\[(\d+)/(\d+)\] (\S+) .* \.\. (.+)$", line)
        if match:
            out[match.group(3)] = match.group(4)
    return out


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    base = tmp_path_factory.mktemp("first-hour")
    repo = base / "repo"
    done = subprocess.run(["git", "clone", "-q", str(ROOT), str(repo)], capture_output=True,
                          text=True, timeout=300)
    if done.returncode != 0:
        pytest.skip(f"cannot clone the repository: {done.stderr.strip()}")
    (base / "home").mkdir()
    (base / "tmp").mkdir()
    env = dict(os.environ, HOME=str(base / "home"), TMPDIR=str(base / "tmp"),
               PYTHONPATH=str(repo))   # the clone's hitops, the shared environment's packages
    env.pop("HITOPS_CASA_LOG", None)
    before = _tree(repo)
    first = runner("recipes/fpt-demo.yml", cwd=repo, env=env)
    return {"base": base, "repo": repo, "env": env, "before": before, "first": first,
            "after": _tree(repo)}


@pytest.mark.slow
def test_demo_is_quiet_and_ends_with_the_answer(clone):
    done = clone["first"]
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    lines = done.stdout.splitlines()
    # make run adds five lines (the make command and four set-up lines)
    assert len(lines) <= 50, done.stdout
    assert done.stderr.strip() == ""
    statuses = _statuses(done.stdout)
    # every step, in order (a recipe may have more than these)
    assert [s for s in statuses if s in DEMO_STEPS] == DEMO_STEPS
    assert all(re.fullmatch(r"[\d.]+ s|\d+ min \d+ s", s) for s in statuses.values()), statuses
    text = done.stdout
    assert "Fractional peak-flux recovery" in text and "PWC (PWC_DATA)" in text
    assert re.search(r"raw \(DATA\)\s+no source", text)           # no number for noise
    assert "Coherence C(60 s) per baseline" in text
    tail = "\n".join(lines[-8:])
    # the run ends by naming its page
    assert lines[-1].startswith("Page:        out/demo/index.html"), lines[-1]
    for key in ("Summary:     out/demo/peak-flux.md", "Plots:       out/demo/diagnose/plots/",
                "Images:      out/demo/images/", "Logs:        out/demo/logs/run-"):
        assert key in tail, tail
    # nothing Stimela, CASA or WSClean printed reached the terminal
    for noise in ("STIMELA", "SEVERE", "FITS card", "WSClean version", "Deprecat",
                  "Insufficient unflagged"):
        assert noise not in text


@pytest.mark.slow
def test_demo_leaves_nothing_outside_out(clone):
    assert clone["first"].returncode == 0
    new = clone["after"] - clone["before"]
    # Python's bytecode caches are the interpreter's, ignored by git
    outside = sorted(p for p in new if not p.startswith("out") and "__pycache__" not in p)
    assert outside == [], outside
    repo = clone["repo"]
    logs = repo / "out" / "demo" / "logs"
    assert (logs / "log-stimela.txt").is_file() and (logs / "stimela.config.deps").is_file()
    latest = logs / "latest"
    assert (latest / "output.txt").is_file() and (latest / "casa.log").is_file()
    # CASA's log is whole there (no /tmp/hitops-casa-<pid>.log per step any more)
    assert "Begin Task: fringefit" in (latest / "casa.log").read_text()
    assert list((clone["base"] / "tmp").iterdir()) == []
    # HOME holds only the tools' caches (Stimela's configuration cache, matplotlib's fonts)
    home = clone["base"] / "home"
    top = {p.name for p in home.iterdir()}
    assert top <= {".cache", ".config", ".stimela"}, top
    assert not (home / ".casa").exists() and not (home / ".cache" / "hitops").exists()


@pytest.mark.slow
def test_demo_reruns_exactly_what_a_changed_parameter_affects(clone):
    assert clone["first"].returncode == 0
    repo, env = clone["repo"], clone["env"]
    out = repo / "out" / "demo"
    same = runner("recipes/fpt-demo.yml", cwd=repo, env=env)
    assert same.returncode == 0, same.stdout[-3000:]
    assert set(_statuses(same.stdout).values()) == {"up to date"}
    # a diagnose parameter: diagnose and the table that reads its summary
    table_before = (out / "peak-flux.json").stat().st_mtime_ns
    plots = runner("recipes/fpt-demo.yml", "plots=coherence", cwd=repo, env=env)
    assert plots.returncode == 0, plots.stdout[-3000:]
    ran = {k for k, v in _statuses(plots.stdout).items() if v != "up to date"}
    assert ran == {"diagnose", "compare"}, plots.stdout
    assert (out / "peak-flux.json").stat().st_mtime_ns > table_before
    fresh_numbers = _numbers(json.loads((out / "peak-flux.json").read_text()))
    # a calibration parameter: everything from fringefit on, not the simulation
    sim_before = (out / "sim-86.ms").stat().st_mtime_ns
    fringe = runner("recipes/fpt-demo.yml", "plots=coherence", "fringefit_solint=60s",
                    cwd=repo, env=env)
    assert fringe.returncode == 0, fringe.stdout[-3000:]
    statuses = _statuses(fringe.stdout)
    assert statuses["simulate"] == "up to date"
    assert all(statuses[k] != "up to date" for k in DEMO_STEPS[1:]), statuses
    assert (out / "sim-86.ms").stat().st_mtime_ns == sim_before
    assert json.loads((out / "params" / "fringefit.json").read_text())["inputs"][
        "fringefit_solint"] == "60s"
    # back at 20 s: every number of the table is the first run's again (each step starts
    # from the flags as simulated, kept as a CASA flag version; docs/recipes.md)
    back = runner("recipes/fpt-demo.yml", "plots=coherence", cwd=repo, env=env)
    assert back.returncode == 0, back.stdout[-3000:]
    assert _numbers(json.loads((out / "peak-flux.json").read_text())) == fresh_numbers
    # and a misspelt one changes nothing
    bad = runner("recipes/fpt-demo.yml", "fringefit_soltint=30s", cwd=repo, env=env)
    assert bad.returncode == 2 and "did you mean 'fringefit_solint'" in bad.stderr


def _numbers(table, path=""):
    """Every number of a peak-flux.json, by its place (paths to files left out)."""
    if isinstance(table, dict):
        return {k: v for key, value in table.items() for k, v in _numbers(value, f"{path}/{key}").items()}
    if isinstance(table, list):
        return {k: v for i, value in enumerate(table) for k, v in _numbers(value, f"{path}[{i}]").items()}
    return {path: table} if isinstance(table, (int, float)) and not isinstance(table, bool) else {}


# ---------------------------------------------------------------------------
# two environments (two clones' .venv) on one machine

FITS_2x2 = b"".join(card.ljust(80).encode() for card in (
    "SIMPLE  =                    T", "BITPIX  =                  -32",
    "NAXIS   =                    2", "NAXIS1  =                    2",
    "NAXIS2  =                    2", "CTYPE1  = 'RA---SIN'", "CRPIX1  =                   1.",
    "CRVAL1  =                 187.", "CDELT1  =              -1.E-09", "CUNIT1  = 'deg     '",
    "CTYPE2  = 'DEC--SIN'", "CRPIX2  =                   1.", "CRVAL2  =                  12.",
    "CDELT2  =               1.E-09", "CUNIT2  = 'deg     '", "BUNIT   = 'JY/BEAM '", "END"))

_CASA_CHECK = r"""
import sys
from hitops.casa_env import ensure_casa_offline
config = ensure_casa_offline()
from hitops.casa.runner import run_task
head = run_task("imhead", imagename=sys.argv[1], mode="list")
print("CONFIG", config)
print("SHAPE", [int(n) for n in head["shape"]])
"""


def _environment(path: Path) -> Path:
    """A virtual environment of its own (its own sys.prefix) seeing this one's packages."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True,
                   timeout=120)
    python = path / "bin" / "python"
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    Path(site, "shared-packages.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


@pytest.mark.slow
def test_two_environments_keep_their_own_casa_configuration(tmp_path):
    image = tmp_path / "tiny.fits"
    image.write_bytes(FITS_2x2.ljust(2880, b" ") + b"\0" * 2880)
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, HOME=str(home), PYTHONPATH=str(ROOT))
    for name in ("CASASITECONFIG", "HITOPS_CASA_CONFIG", "HITOPS_CASA_LOG"):
        env.pop(name, None)
    envs = {name: _environment(tmp_path / name / ".venv") for name in ("a", "b")}

    def check(name):
        done = subprocess.run([str(envs[name]), "-c", _CASA_CHECK, str(image)], cwd=tmp_path,
                              capture_output=True, text=True, env=env, timeout=300)
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
        assert "SHAPE [2, 2]" in done.stdout
        return Path(next(l for l in done.stdout.splitlines() if l.startswith("CONFIG"))[7:])

    config_a, config_b = check("a"), check("b")
    assert config_a == tmp_path / "a" / ".venv" / "etc" / "hitops" / "casasiteconfig.py"
    assert config_b == tmp_path / "b" / ".venv" / "etc" / "hitops" / "casasiteconfig.py"
    text_a = config_a.read_text()
    shutil.rmtree(tmp_path / "b")            # the second clone is deleted
    assert check("a") == config_a and config_a.read_text() == text_a
    # nothing per user: no ~/.casa, no ~/.cache/hitops; CASA's log beside the image
    assert not (home / ".casa").exists() and not (home / ".cache" / "hitops").exists()
    assert "Begin Task: imhead" in (tmp_path / "casa.log").read_text()


def test_a_failed_step_shows_its_error_and_casa_counts_not_its_whole_output():
    from hitops.run import failure_lines

    tail = ["### preparing function call:", "# 04:11:53 INFO    CASA gaincal(vis='x.ms')",
            "# 04:11:53 INFO    CASA gaincal: 328 x Insufficient unflagged antennas to proceed "
            "with this solve. (log out/demo/logs/run-1/casa.log)",
            "# Traceback (most recent call last):", '#   File "x.py", line 1, in <module>',
            "# hitops.errors.ExternalToolError: CASA task gaincal failed (SEVERE error(s)):",
            "#   2026-11-24 SEVERE gaincal No valid reference antenna",
            "2026-11-24 04:11:53 STIMELA.fpt-demo.gaincal ERROR: step 'fpt-demo.gaincal' has "
            "failed, aborting the recipe"] + [f"line {i}" for i in range(100)]
    picked = failure_lines(tail)
    assert picked[0].endswith("(log out/demo/logs/run-1/casa.log)")
    assert any("ExternalToolError" in l for l in picked)
    assert any("No valid reference antenna" in l for l in picked)   # the quoted SEVERE line
    assert not any(l.startswith("line ") or "Traceback" in l for l in picked)
    assert failure_lines(["a", "b"]) == ["a", "b"]   # no error line: the step's last lines
