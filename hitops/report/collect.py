"""What a run left in its directory, read into typed facts for the page.

Every reader here takes what exists and says what is missing: the page of a
directory that holds only ``hitops calibrate`` or ``diagnose`` outputs shows those.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

from ..io.flag_versions import FlagVersion, list_versions

log = logging.getLogger("hitops.report")


@dataclass(frozen=True)
class PeakRow:
    """One calibration's image-plane result (a row of peak-flux.json)."""

    label: str
    method: str
    image: Optional[str]
    fit: str
    note: str
    peak_jy: Optional[float]
    peak_err_jy: Optional[float]
    recovery: Optional[float]
    recovery_err: Optional[float]


@dataclass(frozen=True)
class ImageFit:
    """A WSClean image with CASA imfit's result (images/LABEL-imfit.json)."""

    label: str
    fits_path: Path
    fit: Dict


@dataclass(frozen=True)
class CalibrateReport:
    """One ``hitops calibrate`` JSON report."""

    path: Path
    body: Dict


@dataclass(frozen=True)
class RunFacts:
    """Everything the page shows, read from the run's directory."""

    dir: Path
    peak_table: Optional[Path]         # the compare step's JSON table
    peak_rows: List[PeakRow]
    input_peak: Optional[float]
    coherence: Optional[Dict]          # peak-flux.json's coherence section
    diagnose: Optional[Dict]           # diagnose/summary.json
    diagnose_dir: Optional[Path]
    images: List[ImageFit]
    plots: List[Path]
    calibrate_reports: List[CalibrateReport]
    sets: List[Path]                   # the Measurement Sets of the run
    flag_versions: Dict[Path, List[FlagVersion]] = field(default_factory=dict)
    receipts: Dict[str, Dict] = field(default_factory=dict)


def _load(path: Path) -> Optional[Dict]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        log.warning("report: %s could not be read (%s); left off the page", path, err)
        return None


def _peak_rows(table: Optional[Dict]) -> List[PeakRow]:
    rows = []
    for row in (table or {}).get("rows", []):
        rows.append(PeakRow(label=str(row.get("label", "")), method=str(row.get("method", "")),
                            image=row.get("image"), fit=str(row.get("fit", "")),
                            note=str(row.get("note") or ""), peak_jy=row.get("peak_jy"),
                            peak_err_jy=row.get("peak_err_jy"), recovery=row.get("recovery"),
                            recovery_err=row.get("recovery_err")))
    return rows


def _images(folder: Path) -> List[ImageFit]:
    out = []
    for fit_path in sorted(folder.glob("*-imfit.json")):
        fit = _load(fit_path)
        if not fit:
            continue
        label = str(fit.get("label") or fit_path.name[:-len("-imfit.json")])
        image = Path(fit.get("image") or folder / f"{label}-image.fits")
        if not image.is_absolute():
            image = folder / image
        if not image.is_file():
            image = folder / image.name      # the run's directory was moved
        out.append(ImageFit(label=label, fits_path=image, fit=fit))
    return out


def _summary_dirs(run_dir: Path) -> List[Path]:
    found = sorted(p.parent for p in run_dir.glob("*/summary.json")
                   if (p.parent / "coherence-table.txt").is_file())
    return found


def _calibrate_reports(run_dir: Path) -> List[CalibrateReport]:
    out = []
    for path in sorted(run_dir.glob("*.json")):     # SET.hitops-calibrate.json included
        body = _load(path) if path.name not in TABLE_NAMES else None
        # a calibrate report names both sets and its methods; nothing else here does
        if body and "target_ms" in body and "methods" in body:
            out.append(CalibrateReport(path=path, body=body))
    return out


def _sets(run_dir: Path, reports: List[CalibrateReport]) -> List[Path]:
    sets = {Path(r.body["target_ms"]) for r in reports} | {Path(r.body["ref_ms"]) for r in reports}
    sets |= set(run_dir.glob("*.ms")) | set(run_dir.glob("*.ps.zarr"))   # MSv4 stores too
    # a report may name a set relative to where the run started: one path per set
    found = {(s if s.is_dir() else run_dir / s.name).resolve() for s in sets}
    return sorted(s for s in found if s.is_dir())


#: the compare step's table: the demo and wideband recipes name it peak-flux, the paper's summary
TABLE_NAMES = ("peak-flux.json", "summary.json")


def peak_table_path(run_dir: Path) -> Optional[Path]:
    return next((run_dir / n for n in TABLE_NAMES if (run_dir / n).is_file()), None)


def collect(run_dir: Path) -> RunFacts:
    """The facts of the run in ``run_dir``."""
    table_path = peak_table_path(run_dir)
    table = _load(table_path) if table_path else None
    if table is not None and "rows" not in table:
        table, table_path = None, None
    summaries = _summary_dirs(run_dir)
    diagnose_dir = summaries[0] if summaries else None
    diagnose = _load(diagnose_dir / "summary.json") if diagnose_dir else None
    plots = sorted((diagnose_dir / "plots").glob("*.png")) if diagnose_dir else []
    reports = _calibrate_reports(run_dir)
    rows = _peak_rows(table)
    input_peak = next((r.get("input_peak_jy") for r in (table or {}).get("rows", [])
                       if r.get("input_peak_jy")), None)
    sets = _sets(run_dir, reports)
    versions = {s: list_versions(s) for s in sets if list_versions(s)}
    receipts = {}
    for receipt in sorted(run_dir.glob("*/applycal.json")):
        body = _load(receipt)
        if body:
            receipts[str(receipt.relative_to(run_dir))] = body
    return RunFacts(dir=run_dir, peak_table=table_path, peak_rows=rows, input_peak=input_peak,
                    coherence=(table or {}).get("coherence"), diagnose=diagnose,
                    diagnose_dir=diagnose_dir, images=_images(run_dir / "images"),
                    plots=plots, calibrate_reports=reports, sets=sets, flag_versions=versions,
                    receipts=receipts)
