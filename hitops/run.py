"""Run a Stimela recipe quietly and end with the answer.

    python -m hitops.run recipes/fpt-demo.yml [-v] [-f] [name=value ...] [-- STIMELA-RUN-OPTIONS]

What it adds to ``stimela run`` (which it calls):

* **Parameters are checked** against the recipe's inputs before anything runs:
  an unknown name is an error naming the closest valid one (Stimela 2.1.4
  accepts ``fringefit_soltint=30s`` silently and ignores it), and a value that
  is not of the input's type (int, float, bool) is refused.
* **No stale results**, as under plain ``stimela run``: the recipe's first
  step (``params``, ``hitops/recipe_params.py``) writes ``{dir}/params/STEP.json``
  for every step, rewritten only when the values it holds change, and the
  steps list that file in ``depends``; this runner prints which steps'
  parameters changed (the step itself has no progress line).
* **Quiet**: one line per recipe step (step k of n, what it does, how long or
  "up to date"); Stimela's whole output goes to ``{dir}/logs/run-DATE/output.txt``
  beside its per-step logs and CASA's log (``casa.log``); ``{dir}/logs/latest``
  points at the last run.  ``-v`` shows the full output as well.
* **Nothing outside the output directory**: Stimela's own log-stimela.txt and
  stimela.config.deps go to ``{dir}/logs/`` instead of the working directory.
* **The answer at the end**: the peak-flux and coherence table of the
  compare step, then the paths of the summary, the coherence table, the plots
  and the images (a diverged CLEAN or a source-less image is said as such).

Exit status: Stimela's (0 on success), 2 for a bad parameter.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import deque
from datetime import datetime
from pathlib import Path
from typing import Dict, List, Optional, Sequence, TextIO

import yaml

from .errors import HitopsError
from .recipe_params import PARAMS_CAB, RESTORE_STEP, RecipeFile, load_recipe

_STEP_START = re.compile(r"STIMELA\.(?P<logger>[\w.-]+) INFO: processing step '(?P<step>[^']+)'")
#: cabs of the bookkeeping steps: the parameter files and the run's page
BOOKKEEPING_CABS = (PARAMS_CAB, "hitops.report")
_SKIP_FRESH = "all required outputs are OK, skipping this step"
_SKIP_COND = "skipping step based on conditonal settings"   # sic, Stimela 2.1.4
_PARAMS_NOTE = re.compile(r"parameters changed for: [\w, -]+")
_ERROR = re.compile(r"\b(ERROR|CRITICAL|[A-Za-z]*Error:)|CASA \w+: \d+ x |^# hitops: |# hitops [a-z]+: ")


class UsageError(Exception):
    """A bad command line: printed as one line, exit status 2."""


# ---------------------------------------------------------------------------
# parameters

def _type_error(name: str, dtype: str, value) -> Optional[str]:
    if dtype == "int" and (isinstance(value, bool) or not isinstance(value, int)):
        return f"{name}={value!r}: an integer is needed"
    if dtype == "float" and (isinstance(value, bool) or not isinstance(value, (int, float))):
        return f"{name}={value!r}: a number is needed"
    if dtype == "bool" and not isinstance(value, bool):
        return f"{name}={value!r}: true or false is needed"
    return None


def _check_dotted(recipe: RecipeFile, name: str) -> None:
    """A dotted name must start with a step (or config., log.): Stimela 2.1.4 drops
    any other one silently, ``steps.X.params.Y`` included (docs/recipes.md)."""
    head = name.split(".", 1)[0]
    if head in recipe.steps or head in ("config", "log"):
        return
    parts = name.split(".")
    if head == "steps" and len(parts) == 4 and parts[2] == "params" and parts[1] in recipe.steps:
        hint = f"write '{parts[1]}.{parts[3]}=...' "
    else:
        close = difflib.get_close_matches(head, list(recipe.steps), n=1, cutoff=0.6)
        hint = f"did you mean '{close[0]}'? " if close else ""
    raise UsageError(f"'{name}': '{head}' is not a step of recipe {recipe.name} "
                     f"(Stimela would ignore it): {hint}(steps: {', '.join(recipe.steps)})")


def parse_overrides(recipe: RecipeFile, args: Sequence[str]) -> Dict[str, object]:
    """``name=value`` arguments checked against the recipe's inputs.

    Values are read as YAML, as Stimela reads them.  Dotted names
    (``STEP.PARAM=...``, ``config.*``, ``log.*``) go to Stimela, which checks the
    parameter's name; a STEP that is not one of the recipe's is refused here.
    """
    values: Dict[str, object] = {}
    valid = sorted(recipe.inputs)
    for arg in args:
        name, sep, raw = arg.partition("=")
        name = name.strip()
        if not sep or not name:
            raise UsageError(f"'{arg}' is not name=value (recipe inputs: {', '.join(valid)})")
        if "." in name:
            _check_dotted(recipe, name)
            values[name] = raw
            continue
        if name not in recipe.inputs:
            close = difflib.get_close_matches(name, valid, n=1, cutoff=0.6)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise UsageError(f"unknown parameter '{name}' for recipe {recipe.name}: {hint}"
                             f"(valid: {', '.join(valid)}; 'stimela doc {recipe.path}' "
                             "explains each)")
        try:
            value = yaml.safe_load(raw) if raw != "" else ""
        except yaml.YAMLError:
            value = raw
        problem = _type_error(name, str(recipe.inputs[name].get("dtype", "")), value)
        if problem:
            raise UsageError(problem)
        values[name] = value
    return values


def effective_values(recipe: RecipeFile, overrides: Dict[str, object]) -> Dict[str, object]:
    values = {name: schema.get("default") for name, schema in recipe.inputs.items()}
    values.update({k: v for k, v in overrides.items() if "." not in k})
    return values


def substitute(value, values: Dict[str, object]):
    """Evaluate the simple Stimela forms the recipes use: =recipe.X and {recipe.X}."""
    if not isinstance(value, str):
        return value
    if value.startswith("=recipe.") and re.fullmatch(r"=recipe\.\w+", value):
        return values.get(value[len("=recipe."):])
    return re.sub(r"\{recipe\.(\w+)\}", lambda m: str(values.get(m.group(1), m.group(0))), value)


# ---------------------------------------------------------------------------
# progress

def _seconds(s: float) -> str:
    if s < 60:
        return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"
    return f"{int(s // 60)} min {s % 60:02.0f} s"


class Progress:
    """Turns Stimela's output into one line per top-level step.

    The step writing the parameter files is bookkeeping: it gets no line of
    its own, only "parameters changed for: ..." when some (not all) changed.
    """

    def __init__(self, recipe: RecipeFile, out: TextIO, enabled: bool = True):
        self.recipe, self.out, self.enabled = recipe, out, enabled
        # bookkeeping steps (the parameter files, the run's page) get no numbered line
        self.names = [s for s, d in recipe.steps.items() if d.get("cab") not in BOOKKEEPING_CABS]
        self.params_steps = {s for s, d in recipe.steps.items() if d.get("cab") == PARAMS_CAB}
        self.params_note = ""
        self.current: Optional[str] = None
        self.start = 0.0
        self.skip_note = ""
        self.inner_started = 0
        self.inner_skipped = 0
        self.tail: deque = deque(maxlen=400)   # the current step's output
        self.results: Dict[str, str] = {}
        self.width = max(60, min(shutil.get_terminal_size((100, 24)).columns, 120))

    def feed(self, line: str) -> None:
        top = f"STIMELA.{self.recipe.name}"
        match = _STEP_START.search(line)
        if match and match.group("logger") == self.recipe.name:
            self.finish()
            self.begin(match.group("step"))
            return
        self.tail.append(line)
        if self.current is None:
            return
        if match and match.group("logger").startswith(f"{self.recipe.name}.{self.current}"):
            # a sub-recipe's flag restore always runs (recipes/fpt-lib.yml): bookkeeping,
            # not work, so a sub-recipe whose other steps were fresh is still up to date
            if match.group("step") != RESTORE_STEP:
                self.inner_started += 1
        elif f"{top} INFO: {_SKIP_FRESH}" in line:
            self.skip_note = "up to date"
        elif f"{top} INFO: {_SKIP_COND}" in line:
            self.skip_note = "skipped (condition not met)"
        elif _SKIP_FRESH in line or _SKIP_COND in line:
            self.inner_skipped += 1
        elif self.current not in self.names and _PARAMS_NOTE.search(line):
            self.params_note = _PARAMS_NOTE.search(line).group(0).rstrip(", ")

    def begin(self, step: str) -> None:
        self.current, self.start = step, time.monotonic()
        self.skip_note, self.inner_started, self.inner_skipped = "", 0, 0
        self.tail.clear()
        if not self.enabled or step not in self.names:
            return
        k = self.names.index(step) + 1 if step in self.names else 0
        info = str(self.recipe.steps.get(step, {}).get("info", "")).strip()
        # the descriptions start in one column: names padded to this recipe's longest
        name_width = max(10, *(len(name) for name in self.names))
        head = f"[{k}/{len(self.names)}] {step:<{name_width}} "
        room = self.width - len(head) - 22
        if len(info) > room:
            info = info[: max(room - 3, 0)].rstrip() + "..."
        self.out.write(f"{head}{info}")
        self.out.flush()

    def finish(self, failed: bool = False) -> None:
        if self.current is None:
            return
        took = time.monotonic() - self.start
        if failed:
            status = f"FAILED after {_seconds(took)}"
        elif self.skip_note:
            status = self.skip_note
        elif self.inner_started and self.inner_skipped >= self.inner_started:
            status = "up to date"
        else:
            status = _seconds(took)
        self.results[self.current] = status
        if self.enabled and self.current not in self.names:
            # the parameter files: a line only when some changed; the page is named at the
            # end; either only when it failed
            what = "parameter files" if self.current in self.params_steps else "page"
            note = f"{what} ({self.current}) {status}" if failed else (
                self.params_note if self.current in self.params_steps else "")
            self.out.write(f"{note}\n" if note else "")
        elif self.enabled:
            self.out.write(f" .. {status}\n")
        self.out.flush()
        self.current = None


# ---------------------------------------------------------------------------
# the answer

def _rel(path: Path) -> str:
    try:
        return os.path.relpath(path)
    except ValueError:
        return str(path)


def report(recipe: RecipeFile, values: Dict[str, object], logdir: Path, out: TextIO) -> None:
    """The result table and where everything is, from the compare, diagnose and image steps."""
    from .compare.table import text_summary

    compares, diagnoses, image_dirs, pages = [], [], [], []
    for step, sdef in recipe.steps.items():
        params = sdef.get("params") or {}
        cab = sdef.get("cab")
        if cab == "hitops.compare":
            outdir = Path(str(substitute(params.get("outdir", "."), values)))
            compares.append((step, outdir / f"{substitute(params.get('name', 'peak-flux'), values)}"))
        elif cab == "hitops.diagnose":
            diagnoses.append(Path(str(substitute(params.get("outdir", "."), values))))
        elif cab == "hitops.report":
            pages.append(Path(str(substitute(params.get("dir", "."), values))) / "index.html")
        elif sdef.get("recipe") and params.get("dir"):
            image_dirs.append(Path(str(substitute(params["dir"], values))))
    main = next((c for c in compares if c[0] == "compare"), compares[0] if compares else None)
    lines: List[str] = []
    if main and main[1].with_suffix(".json").is_file():
        payload = json.loads(main[1].with_suffix(".json").read_text())
        lines += ["", *text_summary(payload).rstrip("\n").splitlines(), ""]
    for _, stem in compares:
        if stem.with_suffix(".md").is_file():
            lines.append(f"Summary:     {_rel(stem.with_suffix('.md'))} (also .csv, .json)")
    for ddir in diagnoses:
        if (ddir / "coherence-table.txt").is_file():
            lines.append(f"Coherence:   {_rel(ddir / 'coherence-table.txt')}")
        plots = sorted((ddir / "plots").glob("*.png"))
        if plots:
            kinds = sorted({p.name.split("-")[0] for p in plots})
            lines.append(f"Plots:       {_rel(ddir / 'plots')}/ ({len(plots)} PNG: "
                         f"{', '.join(k + '-*' for k in kinds)})")
    # several image sub-recipes may share one directory (the demo's images and
    # images_table): list each directory's images once
    for idir in dict.fromkeys(image_dirs):
        lines += image_lines(idir)
    lines.append(f"Logs:        {_rel(logdir)}/ (output.txt, casa.log, one log per step)")
    for page in pages:
        if page.is_file():
            lines.append(f"Page:        {_rel(page)} (everything above on one page: open it in a "
                         "browser)")
    out.write("\n".join(lines) + "\n")


def image_lines(idir: Path) -> List[str]:
    fits = sorted(idir.glob("*-imfit.json"))
    if not fits:
        return []
    good, notes = [], []
    for path in fits:
        try:
            fit = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        label = str(fit.get("label") or path.name[: -len("-imfit.json")])
        method = fit.get("method", "gaussian")
        if method == "max-pixel" and fit.get("diverged", "diverged" in str(fit.get("reason", ""))):
            notes.append(f"{label}: CLEAN diverged, look at the dirty image "
                         f"{Path(str(fit.get('fallback_image', ''))).name}")
        elif method == "max-pixel":
            notes.append(f"{label}: fit did not converge (brightest dirty-image pixel reported)")
        elif method == "no-source":
            good.append(label)
            notes.append(f"{label}: no source above the noise")
        else:
            good.append(label)
    lines = []
    if good:
        names = good[0] if len(good) == 1 else "{" + ",".join(good) + "}"
        lines.append(f"Images:      {_rel(idir)}/{names}-image.fits")
    for note in notes:
        lines.append(f"             {note}")
    return lines


# ---------------------------------------------------------------------------
# running Stimela

def failure_lines(tail: Sequence[str], limit: int = 15) -> List[str]:
    """What a failed step said that matters: error lines (with their indented
    continuation) and the CASA warning counts; else the step's last lines."""
    picked: List[str] = []
    follow = 0
    for line in tail:
        if _ERROR.search(line):
            picked.append(line)
            follow = 10
        elif follow and line.startswith("#  "):
            picked.append(line)
            follow -= 1
        else:
            follow = 0
    return (picked or list(tail))[-limit:]


def _stimela() -> str:
    here = Path(sys.executable).with_name("stimela")
    found = str(here) if here.exists() else shutil.which("stimela")
    if not found:
        raise UsageError("stimela is not installed in this environment: run 'make setup'")
    return found


def stimela_command(recipe: RecipeFile, overrides: Sequence[str], logs_root: Path,
                    logdir: Path, force: bool, extra: Sequence[str]) -> List[str]:
    return [_stimela(), "-B", "-s", f"opts.log.dir={logs_root}", "run",
            "-c", f"opts.log.dir={logdir}",
            *(["-f"] if force else []), *extra, str(recipe.path), *overrides]


def child_environment(logdir: Path) -> Dict[str, str]:
    env = dict(os.environ)
    bindir = str(Path(sys.executable).parent)
    # the python-flavour cabs run `python`, the binary ones `hitops` and `wsclean`
    env["PATH"] = f"{bindir}{os.pathsep}{env.get('PATH', '')}"
    cache = Path(sys.prefix) / "numba-cache"
    if "NUMBA_CACHE_DIR" not in env and cache.is_dir():
        env["NUMBA_CACHE_DIR"] = str(cache)
    env["HITOPS_CASA_LOG"] = str((logdir / "casa.log").resolve())
    env["COLUMNS"] = "200"   # Stimela wraps its lines at the terminal width (80 in a pipe)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _point_latest(logs_root: Path, logdir: Path) -> None:
    """{dir}/logs/latest -> the run's log directory."""
    latest = logs_root / "latest"
    try:
        if latest.is_symlink():
            latest.unlink()
        if not latest.exists():
            latest.symlink_to(logdir.name)
    except OSError:
        pass   # a file system without symlinks: the run's directory is printed anyway


def run(recipe_path: str, args: Sequence[str], verbose: bool = False, force: bool = False,
        extra: Sequence[str] = (), out: TextIO = sys.stdout) -> int:
    recipe = load_recipe(recipe_path)
    overrides = parse_overrides(recipe, args)
    values = effective_values(recipe, overrides)
    if not values.get("dir"):
        raise UsageError(f"recipe {recipe.name} has no 'dir' input: this runner needs one")
    outdir = Path(str(values["dir"]))
    logs_root = outdir / "logs"
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    logdir = logs_root / f"run-{stamp}"
    n = 1
    while logdir.exists():
        n += 1
        logdir = logs_root / f"run-{stamp}-{n}"
    logdir.mkdir(parents=True)
    _point_latest(logs_root, logdir)
    cmd = stimela_command(recipe, list(args), logs_root, logdir, force, extra)
    progress = Progress(recipe, out, enabled=not verbose)
    what = f"{recipe.name}: {recipe.info}" if recipe.info else recipe.name
    out.write(f"{what}\n")
    out.write(f"output in {_rel(outdir)}/, full log in {_rel(logdir)}/output.txt\n")
    out.flush()
    started = time.monotonic()
    with open(logdir / "output.txt", "w") as full:
        full.write("$ " + " ".join(cmd) + "\n")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                errors="replace", env=child_environment(logdir), bufsize=1)
        try:
            for raw in proc.stdout:
                line = raw.rstrip()
                full.write(line + "\n")
                if verbose:
                    out.write(line + "\n")
                progress.feed(line)
            rc = proc.wait()
        except KeyboardInterrupt:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
            progress.finish(failed=True)
            out.write(f"interrupted; the steps done so far are kept (log {_rel(logdir)})\n")
            return 130
    if rc != 0:
        failed_tail = list(progress.tail)
        progress.finish(failed=True)
        if not verbose:
            out.write("\n".join(["", *failure_lines(failed_tail)]) + "\n")
        out.write(f"\nthe run failed (stimela exit status {rc}); the full output is in "
                  f"{_rel(logdir)}/output.txt\n")
        return rc
    progress.finish()
    out.write(f"done in {_seconds(time.monotonic() - started)}\n")
    report(recipe, values, logdir, out)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: List[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1:]
    parser = argparse.ArgumentParser(
        prog="python -m hitops.run",
        description="Run a Stimela recipe quietly (one line per step; full logs under "
                    "DIR/logs/), refusing unknown parameters and rerunning the steps whose "
                    "parameters changed; ends with the result table and the paths of the "
                    "outputs.",
        epilog="Options after '--' go to 'stimela run' as they are (e.g. -- -s fringefit).")
    parser.add_argument("recipe", help="recipe file, e.g. recipes/fpt-demo.yml")
    parser.add_argument("params", nargs="*", metavar="name=value",
                        help="recipe inputs ('stimela doc RECIPE' lists them)")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="show Stimela's, the tools' and WSClean's full output too")
    parser.add_argument("-f", "--force", action="store_true",
                        help="rerun every step, even those whose outputs are up to date")
    opts = parser.parse_args(argv)
    try:
        return run(opts.recipe, opts.params, verbose=opts.verbose, force=opts.force, extra=extra)
    except (UsageError, HitopsError) as err:
        print(f"hitops run: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
