"""CASA flag versions of a Measurement Set, read and written in CASA's own layout.

CASA keeps saved flags beside a set in ``<vis>.flagversions/``: a text file
``FLAG_VERSION_LIST`` with one ``name : comment`` line per version, and one table
``flags.<name>`` per version holding the set's FLAG and FLAG_ROW columns, row for
row (what ``flagmanager(mode='save')`` writes, checked with casatasks 6.7).  Writing
the same layout here means ``flagmanager(vis, mode='list')`` lists hitops's versions
and ``mode='restore'`` restores them, while a recipe step restores or saves one in
well under a second, without starting CASA.

The recipes use them so that a rerun is a fresh run (docs/recipes.md): the flags as
simulated or imported are kept as ``hitops_original``; every step that flags starts
from the version it declares and keeps its result as a version of its own; every step
that reads flags (imaging, diagnose) restores the version of the branch it looks at.

Unlike CASA's ``save``, which renames an existing version ``NAME.old.<time>``, saving a
version that exists replaces it: a rerun of a step replaces that step's flags.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import List, Sequence

import numpy as np

from ..errors import InputError
from . import tables

log = logging.getLogger("hitops.flags")

LIST_FILE = "FLAG_VERSION_LIST"
#: the version that holds the flags as a set was simulated or imported
ORIGINAL = "hitops_original"
#: rows per block when copying flags (bounds the memory of a large set)
_BLOCK_ROWS = 262_144


@dataclass(frozen=True)
class FlagVersion:
    """One saved version: its name and CASA's comment."""

    name: str
    comment: str


def versions_dir(ms: str | Path) -> Path:
    return Path(str(ms).rstrip("/") + ".flagversions")


def list_versions(ms: str | Path) -> List[FlagVersion]:
    """The versions saved beside ``ms`` in the order of FLAG_VERSION_LIST (none: [])."""
    listing = versions_dir(ms) / LIST_FILE
    if not listing.is_file():
        return []
    out = []
    for line in listing.read_text().splitlines():
        name, sep, comment = line.partition(" : ")
        if sep and name.strip():
            out.append(FlagVersion(name.strip(), comment.strip()))
    return out


def _write_list(ms: str | Path, versions: Sequence[FlagVersion]) -> None:
    listing = versions_dir(ms) / LIST_FILE
    tmp = listing.with_name(LIST_FILE + ".writing")
    tmp.write_text("".join(f"{v.name} : {v.comment}\n" for v in versions))
    os.replace(tmp, listing)


def _check_name(name: str) -> str:
    name = str(name).strip()
    if not name or any(c in name for c in "/ :\n") or name.startswith("."):
        raise InputError(f"flag version name {name!r}: use letters, digits, '_', '-' or '.' "
                         "(no spaces, ':' or '/')")
    return name


def save_version(ms: str | Path, name: str, comment: str) -> FlagVersion:
    """Keep the set's FLAG and FLAG_ROW as version ``name`` (an existing one is replaced)."""
    name = _check_name(name)
    comment = " ".join(str(comment).split())
    folder = versions_dir(ms)
    folder.mkdir(exist_ok=True)
    final = folder / f"flags.{name}"
    staging = folder / f".flags.{name}.writing"
    shutil.rmtree(staging, ignore_errors=True)
    # CASA's layout: FLAG in a TiledShapeStMan, FLAG_ROW in the standard manager
    description = tables.table_description([
        tables.variable_array_column("FLAG", False, 2, "boolean"),
        tables.scalar_column("FLAG_ROW", False, "boolean")])
    managers = {"*1": {"TYPE": "TiledShapeStMan", "NAME": "TiledFlag", "SPEC": {},
                       "COLUMNS": ["FLAG"]}}
    with tables.main_table(str(ms)) as main:
        n_row = main.nrows()
        with tables.new_table(str(staging), description, n_row, managers) as copy:
            for start in range(0, n_row, _BLOCK_ROWS):
                n = min(_BLOCK_ROWS, n_row - start)
                copy.putcol("FLAG", main.getcol("FLAG", start, n), start, n)
                copy.putcol("FLAG_ROW", main.getcol("FLAG_ROW", start, n), start, n)
    shutil.rmtree(final, ignore_errors=True)
    staging.rename(final)
    saved = FlagVersion(name, comment)
    listed = list_versions(ms)
    if any(v.name == name for v in listed):   # replaced where it stood in the list
        listed = [saved if v.name == name else v for v in listed]
    else:
        listed.append(saved)
    _write_list(ms, listed)
    log.info("flags of %s kept as flag version '%s' (%s)", ms, name, comment)
    return saved


def _require(ms: str | Path, name: str) -> Path:
    table = versions_dir(ms) / f"flags.{name}"
    if not (table / "table.dat").is_file():
        have = ", ".join(v.name for v in list_versions(ms)) or "none"
        raise InputError(f"{ms}: no flag version '{name}' in {versions_dir(ms)} (versions: "
                         f"{have}); run the step that saves it first, or rerun the recipe "
                         "from its simulate/import step")
    return table


def read_version(ms: str | Path, names: Sequence[str]) -> tuple:
    """(FLAG, FLAG_ROW) of the union of the versions ``names``, checked against the set."""
    kept = [_require(ms, _check_name(n)) for n in names]
    n_row = tables.row_count(str(ms))
    flag = flag_row = None
    for table in kept:
        with tables.open_table(str(table)) as saved:
            if saved.nrows() != n_row:
                raise InputError(f"{table} has {saved.nrows()} rows but {ms} has {n_row}: the "
                                 "version belongs to an earlier set; rerun the step that saves it")
            f, r = saved.getcol("FLAG"), saved.getcol("FLAG_ROW")
        flag = f if flag is None else flag | f
        flag_row = r if flag_row is None else flag_row | r
    return flag, flag_row


def restore_versions(ms: str | Path, names: Sequence[str]) -> float:
    """Set FLAG and FLAG_ROW to the union of the saved versions ``names``; return the
    fraction of samples now flagged."""
    names = [n for n in names if str(n).strip()]
    if not names:
        raise InputError("no flag version named to restore")
    flag, flag_row = read_version(ms, names)
    with tables.main_table(str(ms), writable=True) as main:
        if main.getcol("FLAG", 0, 1).shape[1:] != flag.shape[1:]:
            raise InputError(f"{ms}: FLAG's shape differs from flag version "
                             f"'{names[0]}'s; rerun the step that saves it")
        main.putcol("FLAG", flag)
        main.putcol("FLAG_ROW", flag_row)
    log.info("FLAG of %s restored from flag version%s %s", ms, "s" if len(names) > 1 else "",
             " | ".join(f"'{n}'" for n in names))
    return flagged_fraction(flag, flag_row)


def drop_all(ms: str | Path) -> None:
    """Remove every saved version (a set written anew makes them meaningless)."""
    shutil.rmtree(versions_dir(ms), ignore_errors=True)


def keep_original(ms: str | Path, how: str) -> FlagVersion:
    """A set just written or imported: its stale versions dropped, its flags kept."""
    drop_all(ms)
    return save_version(ms, ORIGINAL, f"flags as {how} (hitops)")


def split_names(text) -> List[str]:
    """A version list given as 'a,b' or a list."""
    if text is None:
        return []
    items = text if isinstance(text, (list, tuple)) else str(text).split(",")
    return [str(i).strip() for i in items if str(i).strip()]


def flagged_fraction(flag: np.ndarray, flag_row: np.ndarray) -> float:
    """Fraction of samples flagged, FLAG_ROW folded into FLAG (for logs and the run's page)."""
    merged = flag | flag_row[:, None, None]
    return float(merged.mean()) if merged.size else 0.0


def restore_step(vis: str, versions) -> dict:
    """The recipes' flag step (cab hitops.flags.restore): FLAG set to the union of
    ``versions`` before a step that reads FLAG but cannot be told a version (WSClean)."""
    return {"flagged_fraction": restore_versions(vis, split_names(versions))}
