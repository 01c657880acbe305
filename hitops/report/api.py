"""``hitops report DIR``: write DIR/index.html, the page of one run (docs/report.md)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Dict, Optional

from ..errors import InputError
from ..io.flag_versions import flagged_fraction, read_version
from .collect import RunFacts, collect
from .images import render_row
from .page import verdict, write_page
from .provenance import gather
from .steps import find_log_dir, read_steps

log = logging.getLogger("hitops.report")

#: the folder beside the page that holds its pictures
ASSETS = "report"


def _version_fractions(facts: RunFacts) -> Dict[Path, Dict[str, float]]:
    """Fraction of each kept flag version's samples that are flagged, per set."""
    out: Dict[Path, Dict[str, float]] = {}
    for ms, versions in facts.flag_versions.items():
        for version in versions:
            try:
                fraction = flagged_fraction(*read_version(ms, [version.name]))
            except InputError as err:
                log.warning("report: %s", err)
                continue
            out.setdefault(ms, {})[version.name] = fraction
    return out


def _recipe_name(recipe: Optional[Path]) -> str:
    if not recipe:
        return ""
    from ..recipe_params import load_recipe

    return load_recipe(recipe).name


def report(dir, recipe=None, logs=None, title=None) -> dict:
    """Write ``dir/index.html`` from what the run left in ``dir``; return its path and verdict."""
    started = time.perf_counter()
    run_dir = Path(dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir} is not a directory: give the run's output directory "
                         "(a recipe's dir=)")
    recipe_path = Path(recipe) if recipe else None
    if recipe_path and not recipe_path.is_file():
        raise InputError(f"--recipe {recipe}: no such file")
    facts = collect(run_dir)
    if not (facts.peak_rows or facts.diagnose or facts.calibrate_reports or facts.images):
        raise InputError(f"{run_dir} holds no peak-flux.json, diagnose summary, hitops calibrate "
                         "report or image fit: nothing to show (give a recipe's dir=)")
    name = _recipe_name(recipe_path)
    steps = read_steps(find_log_dir(run_dir, name, logs), name, ())
    order = [r.label for r in facts.peak_rows]
    images = sorted(facts.images, key=lambda i: (order.index(i.label) if i.label in order
                                                  else len(order), i.label))
    pictures = render_row(images, run_dir / ASSETS, facts.input_peak)
    prov = gather(run_dir, recipe_path, facts.sets)
    page = run_dir / "index.html"
    heading = title or (f"HITOPS run: {name}" if name else "HITOPS run")
    write_page(page, heading, facts, pictures, steps, prov, _version_fractions(facts),
               subtitle=f"{run_dir.resolve()} · {steps.started or 'time unknown'}")
    log.info("report: %s written in %.1f s (%d images, %d plots, %d steps)", page,
             time.perf_counter() - started, len(pictures), len(facts.plots), len(steps.steps))
    return {"page": str(page), "verdict": verdict(facts)}
