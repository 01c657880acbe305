"""The parameter file of every recipe step, written by the recipe's own first step.

Stimela's ``skip_if_outputs: fresh`` compares file modification times, not
parameter values, so a changed parameter alone reruns nothing.  Each HITOPS
recipe therefore starts with a ``params`` step (cab ``hitops.params``,
``cabs/hitops-pipeline.yml``) that always runs and calls
:func:`write_recipe_params`: for every other step it writes
``{dir}/params/STEP.json``, the values of the recipe inputs the step's
definition names (``recipe.NAME``) and the definition itself (with the
sub-recipe's, for a step that runs one), rewriting a file only when its
content changes.  The steps list their file in ``depends``, so a file's
modification time is that of the step's last parameter change, and a step
whose outputs are older reruns, and with it everything that reads them.

Because the recipe writes the files, this holds under plain ``stimela run``
(with ``--slurm``, in the container image) as under ``python -m hitops.run``.
Stimela gives the step the recipe's file (``${self:path}``, resolved by
scabha's config loader to the path the recipe was loaded from) and the value
of every input (a mapping of ``=recipe.NAME`` formulas, evaluated by Stimela
after the command line's ``name=value`` assignments).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Mapping

import yaml

from .errors import InputError

#: Top-level sections of a recipe file that are configuration, not recipes
CONFIG_SECTIONS = {"_include", "_use", "opts", "lib", "cabs", "vars", "images", "run"}

#: Recipe inputs that do not change what a step computes: where the outputs go
#: (the parameter files live there already) and how many threads compute them
NOT_DEFINING = {"dir", "threads"}

#: What the recipes pass for an optional input left unset
#: (``=IFSET(recipe.NAME, SELF, "<unset>")``: Stimela refuses UNSET inside a mapping)
UNSET_MARK = "<unset>"

#: The cab of the step that writes the parameter files (it has no file of its own)
PARAMS_CAB = "hitops.params"

#: The image-fit sub-recipe's step that restores a branch's flag version before WSClean
#: (recipes/fpt-lib.yml): it always runs, and is bookkeeping rather than work
RESTORE_STEP = "restore_flags"

_RECIPE_REF = re.compile(r"\brecipe\.([A-Za-z_]\w*)")


@dataclass
class RecipeFile:
    path: Path
    name: str
    info: str
    inputs: Dict[str, dict]
    steps: Dict[str, dict]
    libs: Dict[str, dict] = field(default_factory=dict)

    def referenced_inputs(self, step: str) -> List[str]:
        """The recipe inputs a step's definition refers to (recipe.NAME)."""
        text = yaml.safe_dump(self.steps[step], sort_keys=True)
        return sorted({m for m in _RECIPE_REF.findall(text) if m in self.inputs})

    def parameter_steps(self) -> List[str]:
        """The steps that get a parameter file: all but the one writing them."""
        return [s for s, d in self.steps.items() if d.get("cab") != PARAMS_CAB]


def _load_yaml(path: Path) -> dict:
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as err:
        raise InputError(f"cannot read the recipe {path}: {err.strerror}") from err
    except yaml.YAMLError as err:
        raise InputError(f"{path} is not valid YAML: {err}") from err
    if not isinstance(doc, dict):
        raise InputError(f"{path} is not a Stimela recipe file (no sections)")
    return doc


def load_recipe(path: str | Path) -> RecipeFile:
    """The recipe defined in ``path``, with the sub-recipes its includes define."""
    path = Path(path)
    doc = _load_yaml(path)
    names = [k for k, v in doc.items() if k not in CONFIG_SECTIONS and isinstance(v, dict)
             and "steps" in v]
    if len(names) != 1:
        raise InputError(f"{path} defines {len(names)} recipes ({', '.join(names) or 'none'}); "
                         "a file with exactly one is needed")
    body = doc[names[0]]
    libs: Dict[str, dict] = {}
    for include in doc.get("_include") or []:
        inc = (path.parent / str(include)) if not os.path.isabs(str(include)) else Path(include)
        if inc.is_file():
            libs.update(((_load_yaml(inc).get("lib") or {}).get("recipes") or {}))
    libs.update(((doc.get("lib") or {}).get("recipes") or {}))
    return RecipeFile(path=path, name=names[0], info=str(body.get("info", "")),
                      inputs=dict(body.get("inputs") or {}), steps=dict(body.get("steps") or {}),
                      libs=libs)


def _without_info(obj):
    if isinstance(obj, dict):
        return {k: _without_info(v) for k, v in obj.items() if k != "info"}
    if isinstance(obj, list):
        return [_without_info(v) for v in obj]
    return obj


def step_parameters(recipe: RecipeFile, step: str, values: Mapping[str, object]) -> dict:
    """What defines a step's outputs: the input values it uses and its definition."""
    definition = recipe.steps[step]
    payload = {
        "recipe": recipe.name,
        "step": step,
        "inputs": {k: values.get(k) for k in recipe.referenced_inputs(step)
                   if k not in NOT_DEFINING},
        "definition": _without_info(definition),
    }
    sub = definition.get("recipe") if isinstance(definition, dict) else None
    if isinstance(sub, str) and sub in recipe.libs:
        payload["sub_recipe"] = _without_info(recipe.libs[sub])
    return payload


def write_parameter_files(recipe: RecipeFile, values: Mapping[str, object],
                          outdir: Path) -> List[str]:
    """Write {outdir}/params/STEP.json for every step; return the steps whose file changed.

    A file is rewritten only when its content changes (then atomically, so a
    reader never sees half a file), so its modification time is the time the
    step's parameters last changed.
    """
    pdir = Path(outdir) / "params"
    pdir.mkdir(parents=True, exist_ok=True)
    changed = []
    for step in recipe.parameter_steps():
        text = json.dumps(step_parameters(recipe, step, values), indent=2, sort_keys=True,
                          default=str) + "\n"
        path = pdir / f"{step}.json"
        if path.is_file() and path.read_text() == text:
            continue
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(text)
        tmp.replace(path)
        changed.append(step)
    return changed


def recipe_values(recipe: RecipeFile, values: Mapping[str, object]) -> Dict[str, object]:
    """The values Stimela passed, checked against the recipe's inputs (unset -> None).

    A recipe whose ``params`` step leaves an input out (or names one it does
    not have) would silently stop rerunning the steps using it: refused.
    """
    missing = sorted(set(recipe.inputs) - set(values))
    extra = sorted(set(values) - set(recipe.inputs))
    if missing or extra:
        what = "; ".join(part for part in (
            f"no value for {', '.join(missing)}" if missing else "",
            f"{', '.join(extra)} not an input of the recipe" if extra else "") if part)
        raise InputError(f"{recipe.path}: the params step's 'values' must list every input of "
                         f"recipe {recipe.name} as NAME: =recipe.NAME ({what})")
    return {k: (None if v == UNSET_MARK else v) for k, v in values.items()}


def write_recipe_params(recipe_file: str, outdir: str, values: Dict[str, object]) -> dict:
    """The ``hitops.params`` cab: write the parameter files of ``recipe_file``'s steps.

    Prints which steps' parameters changed (``python -m hitops.run`` shows
    that line) and returns them as the cab's ``changed`` output.
    """
    recipe = load_recipe(recipe_file)
    changed = write_parameter_files(recipe, recipe_values(recipe, values), Path(outdir))
    n_steps = len(recipe.parameter_steps())
    if not changed:
        print(f"parameters unchanged for all {n_steps} steps ({outdir}/params)")
    elif len(changed) == n_steps:
        print(f"parameters written for all {n_steps} steps ({outdir}/params)")
    else:
        print(f"parameters changed for: {', '.join(changed)}")
    return {"changed": changed}
