"""UVFITS and FITS-IDI inputs as Measurement Sets: converted once, checked first, never half-written.

``hitops calibrate REF TARGET`` takes a Measurement Set, a UVFITS file or a
FITS-IDI file for each band.  :func:`ensure_ms` returns a Measurement Set for
any of them:

* a Measurement Set is returned as it is;
* a UVFITS file is converted with CASA ``importuvfits``, a FITS-IDI file with
  CASA ``importfitsidi``, into ``<workdir>/<file name>.ms`` (``workdir``
  defaults to the input's directory); a plain UVFITS file is read directly
  instead (:mod:`hitops.io.uvfits_read`, the same set, faster).  CASA is used
  rather than pyuvdata because it reads every dialect the EHT and VLBI
  pipelines write (AIPS, EHT-HOPS/eht-imaging, CASA's own exportuvfits,
  correlator FITS-IDI), is already a dependency, and was as fast as needed
  (about 2 s for a 1.2 M-row band, docs/interop.md); pyuvdata reads no
  FITS-IDI and would add a dependency for nothing;
* the converted set is reused while it is newer than its source and its record
  (``<ms>.hitops-convert.json``: source path, size, modification time) still
  matches the source, so a second run converts nothing;
* before CASA sees a file it is checked (:mod:`hitops.io.detect`: one line
  naming the file and the remedy): not FITS, truncated, no antenna table,
  several frequency setups (FQ rows), IFs the FQ table does not describe.  Several
  IFs go in as several spectral windows (CASA importuvfits/importfitsidi).  CASA can abort the whole
  process on some malformed files, so these checks come first;
* the set is written under a temporary name beside its final place and
  renamed last, so a failed conversion leaves no half-written Measurement Set,
  and the source file is only ever read;
* scans: UVFITS has no scan column (AIPS keeps scans in an NX table CASA does
  not read), so after the import every time gap longer than
  ``SCAN_GAP_INTEGRATIONS`` integrations starts a new SCAN_NUMBER (besides
  the scans CASA found); the number of scans is logged and recorded.

Station codes: importuvfits names the antennas '1', '2', ... and keeps the
codes (AIPS ANNAME) in ANTENNA::STATION; :mod:`hitops.io.stations` reads them
from there, so the converted sets pair by code like any other.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from ..errors import ExternalToolError, InputError, MeasurementSetError
from .detect import check_fitsidi, check_uvfits, detect_format, hdus_of
from .flag_versions import keep_original
from .uvfits_read import NeedsCasa, import_uvfits_direct
from . import tables

log = logging.getLogger("hitops.io")

#: a time gap longer than this many integrations starts a new scan in a converted set
SCAN_GAP_INTEGRATIONS = 5.0
#: suffix of the record written beside each converted set
RECORD_SUFFIX = ".hitops-convert.json"


@dataclass
class Conversion:
    """What :func:`ensure_ms` did for one input."""

    source: str                     # the path given
    format: str                     # "ms", "uvfits" or "fitsidi"
    ms: str                         # the Measurement Set to use
    converted: bool = False         # converted by this call
    reused: bool = False            # an earlier conversion was reused
    seconds: float = 0.0            # conversion time (0 when nothing was done)
    n_scans: int = 0                # scans in the converted set
    scans_added: int = 0            # scans the time gaps added to CASA's
    scan_gap_s: float = 0.0         # the gap that starts a scan
    tool: str = ""                  # "casatasks.importuvfits" / "casatasks.importfitsidi"
    notes: List[str] = field(default_factory=list)

    def as_dict(self) -> Dict:
        return asdict(self)


# ---------------------------------------------------------------- scans

@dataclass(frozen=True)
class Scans:
    """The scans of a converted set, after :func:`assign_scans`."""

    n_scans: int
    scans_added: int                # scans the time gaps added to the importer's
    gap_s: float                    # a gap longer than this starts a scan


def assign_scans(ms: str, gap_integrations: float = SCAN_GAP_INTEGRATIONS) -> Scans:
    """SCAN_NUMBER := a new scan at every time gap longer than ``gap_integrations`` integrations.

    The integration is the median INTERVAL (or the median step between distinct
    times when INTERVAL is 0).  Scans CASA already distinguished stay separate.
    """
    with tables.main_table(ms, writable=True) as t:
        if t.nrows() == 0:
            return Scans(0, 0, 0.0)
        time_ = t.getcol("TIME")
        scan = t.getcol("SCAN_NUMBER")
        interval = t.getcol("INTERVAL")
        utimes, inverse = np.unique(time_, return_inverse=True)
        steps = np.diff(utimes)
        positive = interval[interval > 0]
        dt = (float(np.median(positive)) if positive.size
              else float(np.median(steps)) if steps.size else 1.0)
        gap_s = float(gap_integrations) * dt
        # CASA's scan of each distinct time (the largest, should rows disagree)
        scan_of_time = np.zeros(utimes.size, np.int64)
        np.maximum.at(scan_of_time, inverse, scan.astype(np.int64))
        new = np.zeros(utimes.size, bool)
        new[1:] = (steps > gap_s) | (np.diff(scan_of_time) != 0)
        numbers = 1 + np.cumsum(new)
        n_before = np.unique(scan_of_time).size
        n_after = int(numbers[-1])
        if not np.array_equal(numbers[inverse], scan):
            t.putcol("SCAN_NUMBER", numbers[inverse].astype(np.int32))
    return Scans(n_after, max(0, n_after - n_before), gap_s)


# ---------------------------------------------------------------- conversion

def _source_stamp(path: str) -> Dict:
    st = os.stat(path)
    return {"source": os.path.realpath(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def converted_path(path, workdir: Optional[str] = None) -> Path:
    """Where the Measurement Set converted from ``path`` lives: ``<workdir>/<name>.ms``."""
    p = Path(path)
    folder = Path(workdir) if workdir else p.resolve().parent
    return folder / (p.name + ".ms")


def record_of(ms) -> Optional[Dict]:
    """The conversion record beside a converted set (None for any other set)."""
    rec = Path(str(ms).rstrip("/") + RECORD_SUFFIX)
    try:
        return json.loads(rec.read_text())
    except (OSError, ValueError):
        return None


def _reusable(path: str, dest: Path) -> Optional[Dict]:
    if not (dest / "table.dat").is_file():
        return None
    record = record_of(dest)
    if not record:
        return None
    stamp = _source_stamp(path)
    if any(record.get(k) != v for k, v in stamp.items()):
        return None
    # "newer than its source": the set was written after the file last changed
    if os.stat(dest / "table.dat").st_mtime_ns < stamp["mtime_ns"]:
        return None
    return record


def ensure_ms(path, role: str = "input", workdir: Optional[str] = None,
              overwrite: bool = False) -> Conversion:
    """A Measurement Set for ``path`` (an MS, a UVFITS or a FITS-IDI file), converting once.

    ``workdir``: where converted sets go (default: beside the input).  A set
    converted earlier from the same, unchanged file is reused; ``overwrite``
    converts again anyway.  A set at the destination that hitops did not
    convert from this file is never replaced: the error says to remove it or
    to pick another ``workdir``.
    """
    fmt = detect_format(path, role)
    if fmt == "ms":
        return Conversion(source=str(path), format="ms", ms=str(path).rstrip("/"))
    return _ensure_at(str(path), converted_path(path, workdir), fmt, role, overwrite)


def _ensure_at(path: str, dest: Path, fmt: str, role: str, overwrite: bool,
               reader: str = "auto") -> Conversion:
    """The conversion of ``path`` at ``dest``: reused when current, else (re)converted."""
    if not overwrite:
        record = _reusable(path, dest)
        if record:
            log.info("%s: using %s, converted from it earlier (%d scans)", path, dest,
                     int(record.get("n_scans", 0)))
            return Conversion(source=path, format=fmt, ms=str(dest), reused=True,
                              n_scans=int(record.get("n_scans", 0)),
                              scans_added=int(record.get("scans_added", 0)),
                              scan_gap_s=float(record.get("scan_gap_s", 0.0)),
                              tool=str(record.get("tool", "")))
    if dest.exists():
        record = record_of(dest)
        if not record and not overwrite:
            raise InputError(
                f"{role} '{path}' would be converted to '{dest}', which exists and was not "
                "converted by hitops from this file; remove it, or pass --workdir to "
                "convert elsewhere")
        if record and record.get("source") != os.path.realpath(path) and not overwrite:
            raise InputError(
                f"{role} '{path}' would be converted to '{dest}', which hitops converted from "
                f"another file ({record.get('source')}); pass --workdir to convert elsewhere")
    return convert(path, dest, fmt, role, reader=reader)


def convert(path, dest, fmt: Optional[str] = None, role: str = "input",
            gap_integrations: float = SCAN_GAP_INTEGRATIONS, reader: str = "auto") -> Conversion:
    """Convert ``path`` (UVFITS or FITS-IDI) into the Measurement Set ``dest`` (replaced).

    Checks the file first, imports it under a temporary name beside ``dest``,
    sets SCAN_NUMBER from the time gaps, writes the record and renames the set
    into place.  The source is opened read-only.

    ``reader`` (UVFITS only): ``auto`` reads a plain file (one source, IF and
    channel; BASELINE and DATE parameters; UTC) directly with numpy and writes
    the set with :mod:`hitops.io.ms_create` (:mod:`hitops.io.uvfits_read`:
    about 4x faster than CASA and no casatasks start-up; station codes in
    ANTENNA::NAME, scans from the AIPS NX table), and hands anything else to
    CASA ``importuvfits``; ``casa`` always uses CASA.  tests/test_convert.py
    checks that both give the same sets.
    """
    path = str(path)
    dest = Path(dest)
    fmt = fmt or detect_format(path, role)
    if reader not in ("auto", "casa"):
        raise InputError(f"UVFITS reader '{reader}': choose auto or casa")
    if fmt == "uvfits":
        summary = check_uvfits(path, role)
    elif fmt == "fitsidi":
        summary = check_fitsidi(path, role)
    else:
        raise InputError(f"{role} '{path}' is a Measurement Set already; nothing to convert")
    _require_writable_folder(path, dest)
    stamp = _source_stamp(path)
    partial = dest.with_name(f".{dest.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    started = time.perf_counter()
    log.info("converting %s (%s, %d rows) into %s", path, fmt, summary.rows, dest)
    try:
        tool = _import(path, partial, fmt, role, reader)
        scans = assign_scans(str(partial), gap_integrations)
        seconds = time.perf_counter() - started
        record = {**stamp, "format": fmt, "tool": tool, "ms": str(dest), "seconds": seconds,
                  "n_scans": scans.n_scans, "scans_added": scans.scans_added,
                  "scan_gap_s": scans.gap_s, "rows": summary.rows}
        _move_into_place(path, partial, dest, record)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    log.info("%s -> %s in %.2f s (%s); %d scans (%d added at time gaps > %.1f s)", path, dest,
             seconds, tool, scans.n_scans, scans.scans_added, scans.gap_s)
    return Conversion(source=path, format=fmt, ms=str(dest), converted=True, seconds=seconds,
                      n_scans=scans.n_scans, scans_added=scans.scans_added,
                      scan_gap_s=scans.gap_s, tool=tool)


def _require_writable_folder(path: str, dest: Path) -> None:
    """The folder of ``dest`` exists (made if needed) and can be written."""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise MeasurementSetError(f"cannot create '{dest.parent}' for the Measurement Set "
                                  f"converted from '{path}' ({err.strerror}); pass --workdir "
                                  "with a writable directory") from err
    if not os.access(dest.parent, os.W_OK):
        raise MeasurementSetError(
            f"'{dest.parent}' is not writable, so '{path}' cannot be converted beside itself; "
            "pass --workdir with a writable directory")


def _import(path: str, partial: Path, fmt: str, role: str, reader: str) -> str:
    """Write the set ``partial`` from the file; return the tool that did it.

    A plain UVFITS file is read directly (``reader`` auto); any other UVFITS
    file goes to CASA importuvfits, every FITS-IDI file to CASA importfitsidi.
    A tool's failure is the one line of an InputError naming the file.
    """
    tool = ""
    try:
        if fmt == "uvfits" and reader == "auto":
            try:
                import_uvfits_direct(path, hdus_of(path, role), str(partial))
                tool = "hitops.io.convert (numpy reader + ms_create)"
            except NeedsCasa as why:
                log.info("%s: %s; reading it with CASA importuvfits", path, why)
                shutil.rmtree(partial, ignore_errors=True)
        if fmt == "uvfits" and not tool:
            tool = "casatasks.importuvfits"
            from ..casa.runner import run_task

            run_task("importuvfits", fitsfile=path, vis=str(partial))
        elif fmt == "fitsidi":
            tool = "casatasks.importfitsidi"
            from ..casa.runner import run_task

            run_task("importfitsidi", fitsidifile=[path], vis=str(partial), constobsid=True)
        if not (partial / "table.dat").is_file():
            raise ExternalToolError(f"CASA {tool} wrote no Measurement Set from '{path}'")
    except ExternalToolError as err:
        raise InputError(f"{role} '{path}' could not be converted ({tool}): "
                         f"{str(err).splitlines()[0]}; check the file with the tool that "
                         "wrote it") from err
    return tool


def _move_into_place(path: str, partial: Path, dest: Path, record: Dict) -> None:
    """The record beside ``dest``, then the set renamed to ``dest`` (replacing an old one)."""
    if dest.exists():
        shutil.rmtree(dest)
    rec_path = Path(str(dest) + RECORD_SUFFIX)
    tmp_rec = rec_path.with_name(rec_path.name + f".{os.getpid()}.tmp")
    tmp_rec.write_text(json.dumps(record, indent=1) + "\n")
    tmp_rec.replace(rec_path)
    try:
        partial.rename(dest)
    except OSError:
        # another run converted the same file at the same time: use its set
        if _reusable(path, dest):
            shutil.rmtree(partial, ignore_errors=True)
        else:
            raise
    else:
        # the flags as imported, as a CASA flag version that recipe steps restore
        keep_original(dest, f"imported from {Path(path).name}")


# ---------------------------------------------------------------- Stimela cab (cabs/interop.yml)

def convert_cab(source: str, ms: str, overwrite: bool = False, reader: str = "auto") -> Dict:
    """``hitops.convert``: the UVFITS or FITS-IDI file ``source`` as the Measurement Set ``ms``.

    An earlier conversion of the unchanged file at ``ms`` is reused unless
    ``overwrite``; a set at ``ms`` that hitops did not convert from ``source`` is
    never replaced.  Returns plain values for Stimela's python flavour.
    """
    fmt = detect_format(source, "input")
    if fmt == "ms":
        raise InputError(f"input '{source}' is a Measurement Set already; give a UVFITS or "
                         "FITS-IDI file (hitops calibrate takes the set itself)")
    c = _ensure_at(str(source), Path(str(ms).rstrip("/")), fmt, "input", bool(overwrite),
                   reader)
    return {"ms": c.ms, "n_scans": int(c.n_scans), "format": c.format, "tool": c.tool,
            "seconds": float(c.seconds), "reused": bool(c.reused)}
