"""What the page needs to rerun the same thing: versions, parameters, checksums, command.

Versions come from the installed distributions' metadata (importlib.metadata) and
``wsclean --version``; the HITOPS commit from git when the package runs from a
checkout; parameters from DIR/params/STEP.json (the recipes' first step writes them)
with the recipe file's defaults beside them; checksums of each input set's DATA and
its flags as simulated or imported (the kept ``hitops_original`` version), which later
steps do not change.
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import subprocess
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from ..io import tables
from ..io.flag_versions import ORIGINAL, versions_dir

#: the distributions whose versions decide a run's numbers
DISTRIBUTIONS = ("hitops", "stimela", "cult-cargo", "casatools", "casatasks", "python-casacore",
                 "dask-ms", "numba", "numpy", "dask")
_UNSET = "<unset>"


@dataclass(frozen=True)
class Parameter:
    """One recipe input: its value in this run and whether it is the recipe's default."""

    name: str
    value: object
    default: object
    is_default: bool


@dataclass(frozen=True)
class SetChecksum:
    """SHA-256 of an input set's DATA and its kept original flags."""

    path: str
    rows: int
    sha256: str
    what: str


@dataclass(frozen=True)
class Provenance:
    versions: Dict[str, str]
    commit: str
    parameters: List[Parameter]
    checksums: List[SetChecksum]
    command: str
    rerun: str


def versions() -> Dict[str, str]:
    out = {}
    for name in DISTRIBUTIONS:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    try:
        done = subprocess.run(["wsclean", "--version"], capture_output=True, text=True,
                              timeout=30)
        line = next((ln for ln in done.stdout.splitlines() if "version" in ln.lower()), "")
        out["wsclean"] = line.strip() or "unknown"
    except (OSError, subprocess.TimeoutExpired):
        out["wsclean"] = "not found"
    return out


def commit() -> str:
    """The git commit of the hitops source (with '+changes' when the tree differs)."""
    source = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(source), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=30)
        if head.returncode != 0:
            return "not a git checkout"
        dirty = subprocess.run(["git", "-C", str(source), "status", "--porcelain", "--", "hitops",
                                "recipes", "cabs"], capture_output=True, text=True, timeout=30)
        return head.stdout.strip() + (" +changes" if dirty.stdout.strip() else "")
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"


def parameters(run_dir: Path, recipe_file: Optional[Path]) -> List[Parameter]:
    """Every recipe input with its value (from DIR/params) and the recipe's default."""
    values: Dict[str, object] = {}
    for path in sorted((run_dir / "params").glob("*.json")):
        try:
            values.update(json.loads(path.read_text()).get("inputs", {}))
        except (OSError, ValueError):
            continue
    defaults: Dict[str, object] = {}
    if recipe_file and recipe_file.is_file():
        from ..recipe_params import load_recipe

        recipe = load_recipe(recipe_file)
        defaults = {k: v.get("default", _UNSET) for k, v in recipe.inputs.items()}
        for name in defaults:
            values.setdefault(name, defaults[name])
        if "dir" in defaults:   # not in the parameter files (they live inside it)
            values["dir"] = str(run_dir)
    out = []
    for name in sorted(values):
        default = defaults.get(name, _UNSET)
        value = _UNSET if values[name] is None else values[name]   # an optional input left unset
        out.append(Parameter(name, value, default, value == default))
    return out


def _digest_set(ms: Path) -> Optional[SetChecksum]:
    try:
        with tables.main_table(str(ms)) as t:
            sha = hashlib.sha256()
            n_row = t.nrows()
            for start in range(0, n_row, 262_144):
                sha.update(t.getcol("DATA", start, min(262_144, n_row - start)).tobytes())
        kept = versions_dir(ms) / f"flags.{ORIGINAL}"
        what = "DATA"
        if (kept / "table.dat").is_file():
            with tables.open_table(str(kept)) as t:
                sha.update(t.getcol("FLAG").tobytes())
                sha.update(t.getcol("FLAG_ROW").tobytes())
            what = f"DATA + flags as kept in {ORIGINAL}"
        return SetChecksum(str(ms), n_row, sha.hexdigest(), what)
    except RuntimeError:
        return None


def _digest_store(ps: Path) -> Optional[SetChecksum]:
    """The input's group of an MSv4 processing set: every partition's ``base`` data group
    (its VISIBILITY and FLAG, the rows as hitops reads them), which a calibrate run never
    writes (its results are data groups of their own)."""
    from ..errors import HitopsError
    from ..io.msv4 import PartitionReader, open_store, read_layout

    try:
        layout = read_layout(open_store(str(ps)))
        sha, n_row = hashlib.sha256(), 0
        for part in layout.partitions:
            for rows in PartitionReader(layout, part.name, "base").chunks(262_144):
                sha.update(rows.data.tobytes())
                sha.update(rows.flag.tobytes())
                n_row += rows.time.size
    except (HitopsError, OSError, KeyError):
        return None
    return SetChecksum(str(ps), n_row, sha.hexdigest(),
                       f"data group base (VISIBILITY + FLAG) of {len(layout.partitions)} "
                       "partition(s)")


def checksums(sets: List[Path]) -> List[SetChecksum]:
    """Each Measurement Set's DATA + original flags, each processing set's input group."""
    from ..io.msv4.store import is_processing_set

    out = []
    for s in sets:
        if (s / "table.dat").is_file():
            out.append(_digest_set(s))
        elif is_processing_set(s):
            out.append(_digest_store(s))
    return [c for c in out if c]


def command_line() -> str:
    """The command that started this run: the parent process's (Stimela's) arguments."""
    try:
        raw = Path(f"/proc/{os.getppid()}/cmdline").read_bytes()
    except OSError:
        return ""
    args = [a.decode(errors="replace") for a in raw.split(b"\0") if a]
    if not any("stimela" in a or "hitops" in a for a in args[:3]):
        return ""
    return " ".join(shlex.quote(a) for a in args)


def rerun_command(recipe_file: Optional[Path], run_dir: Path,
                  params: List[Parameter]) -> Tuple[str, ...]:
    """``stimela run RECIPE dir=DIR name=value ...`` for every input that is not the default."""
    if not recipe_file:
        return ()
    words = ["stimela", "run", str(recipe_file), f"dir={run_dir}"]
    for p in params:
        if p.is_default or p.value == _UNSET or p.name == "dir":
            continue
        value = p.value
        text = (json.dumps(value) if isinstance(value, (list, dict))
                else str(value).lower() if isinstance(value, bool) else str(value))
        words.append(f"{p.name}={text}")
    return tuple(words)


def gather(run_dir: Path, recipe_file: Optional[Path], sets: List[Path]) -> Provenance:
    params = parameters(run_dir, recipe_file)
    rerun = rerun_command(recipe_file, run_dir, params)
    return Provenance(versions=versions(), commit=commit(), parameters=params,
                      checksums=checksums(sets), command=command_line(),
                      rerun=" ".join(shlex.quote(w) for w in rerun))
