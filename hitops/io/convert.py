"""UVFITS and FITS-IDI inputs as Measurement Sets: converted once, checked first, never half-written.

``hitops calibrate REF TARGET`` takes a Measurement Set, a UVFITS file or a
FITS-IDI file for each band.  :func:`ensure_ms` returns a Measurement Set for
any of them:

* a Measurement Set is returned as it is;
* a UVFITS file is converted with CASA ``importuvfits``, a FITS-IDI file with
  CASA ``importfitsidi``, into ``<workdir>/<file name>.ms`` (``workdir``
  defaults to the input's directory).  CASA is used rather than pyuvdata or a
  reader of our own because it reads every dialect the EHT and VLBI pipelines
  write (AIPS, EHT-HOPS/eht-imaging, CASA's own exportuvfits, correlator
  FITS-IDI), is already a dependency, and was as fast as needed (about 2 s for
  a 1.2 M-row band, docs/interop.md); pyuvdata reads no FITS-IDI and would
  add a dependency for nothing;
* the converted set is reused while it is newer than its source and its record
  (``<ms>.hitops-convert.json``: source path, size, modification time) still
  matches the source, so a second run converts nothing;
* before CASA sees a file it is checked here (one line naming the file and
  the remedy, :class:`hitops.errors.InputError`): not FITS, truncated, no
  antenna table, several frequency setups (FQ rows) or IFs.  CASA can abort
  the whole process on some malformed files, so these checks come first;
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

from ..errors import ExternalToolError, InputError, MeasurementSetError, OutputExistsError

log = logging.getLogger("hitops.io")

#: a time gap longer than this many integrations starts a new scan in a converted set
SCAN_GAP_INTEGRATIONS = 5.0
#: suffix of the record written beside each converted set
RECORD_SUFFIX = ".hitops-convert.json"
FITS_BLOCK = 2880


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


# ---------------------------------------------------------------- format detection

def _cards(block: bytes) -> Dict[str, str]:
    """Keyword -> raw value text of the 80-character cards in a header block."""
    out = {}
    for i in range(0, len(block) - 79, 80):
        card = block[i:i + 80].decode("ascii", errors="replace")
        key = card[:8].strip()
        if card[8:10] == "= " and key and key not in out:
            out[key] = card[10:].split("/")[0].strip().strip("'").strip()
    return out


def detect_format(path, role: str = "input") -> str:
    """'ms', 'uvfits' or 'fitsidi'; raise naming the file when it is none of them.

    A path that does not exist or is a directory counts as 'ms': the Measurement
    Set checks that follow say what is wrong with it.
    """
    p = Path(path)
    if not p.is_file():
        return "ms"
    with open(p, "rb") as fh:
        head = fh.read(FITS_BLOCK)
    if not head.startswith(b"SIMPLE  ="):
        raise InputError(f"{role} '{path}' is neither a Measurement Set (a directory) nor a "
                         "FITS file (UVFITS or FITS-IDI); check the path")
    cards = _cards(head)
    if cards.get("GROUPS") == "T" and cards.get("NAXIS1") == "0" and int(cards.get("GCOUNT", "0") or 0) > 0:
        return "uvfits"
    if cards.get("NAXIS") == "0":
        return "fitsidi"
    raise InputError(f"{role} '{path}' is a FITS file but neither UVFITS (random groups) nor "
                     "FITS-IDI (UV_DATA tables); hitops calibrate reads visibilities only")


# ---------------------------------------------------------------- checks before CASA

def _hdus(path: str, role: str):
    """Headers of every HDU with their data offsets and sizes (data not read)."""
    from .fits import read_headers

    size = os.path.getsize(path)
    try:
        out = read_headers(path)
    except (OSError, ValueError) as err:
        raise InputError(f"{role} '{path}' cannot be read as FITS ({err}); the file is "
                         "damaged or truncated: copy it again from its source") from err
    for header, start, n_bytes in out:
        # the data must be in the file; the last block's padding may be missing
        if start + n_bytes > size:
            raise InputError(
                f"{role} '{path}' is truncated: {size} bytes, but its "
                f"{header.get('EXTNAME', 'primary')} data end at byte {start + n_bytes}; copy "
                "the file again from its source")
    return out


def check_uvfits(path, role: str = "UVFITS input") -> Dict:
    """Check a UVFITS file before it is imported; return a summary. One-line errors."""
    hdus = _hdus(str(path), role)
    primary = hdus[0][0]
    naxis = int(primary.get("NAXIS", 0))
    axes = {str(primary.get(f"CTYPE{k}", "")).strip(): int(primary.get(f"NAXIS{k}", 0))
            for k in range(2, naxis + 1)}
    if not primary.get("GROUPS") or "COMPLEX" not in axes:
        raise InputError(f"{role} '{path}' is not UVFITS: no random-group visibilities "
                         "(GROUPS = T, a COMPLEX axis); give a UVFITS file")
    tables = {str(h.get("EXTNAME", "")).strip(): h for h, _, _ in hdus[1:]}
    if "AIPS AN" not in tables:
        raise InputError(
            f"{role} '{path}' has no antenna table (AIPS AN); the stations are unknown and "
            "cannot be paired with the other band: write the file with its AN table (AIPS "
            "FITTP, CASA exportuvfits, eht-imaging save_uvfits)")
    n_if = axes.get("IF", 1)
    if n_if > 1:
        raise InputError(
            f"{role} '{path}' holds {n_if} IFs (spectral windows); hitops calibrate takes one "
            "frequency setup per band: average or split the IFs first (e.g. eht-imaging "
            "load_uvfits averages them; AIPS SPLAT/UVAVG; CASA importuvfits + split)")
    fq = tables.get("AIPS FQ")
    if fq is not None and int(fq.get("NAXIS2", 1)) > 1:
        raise InputError(
            f"{role} '{path}' holds {int(fq['NAXIS2'])} frequency setups (rows of its AIPS FQ "
            "table); hitops calibrate takes one per band: split the file by FREQID first "
            "(AIPS SPLIT, or CASA importuvfits + split spw=...)")
    if int(primary.get("GCOUNT", 0)) == 0:
        raise InputError(f"{role} '{path}' holds no visibilities (GCOUNT = 0)")
    return {"rows": int(primary["GCOUNT"]), "n_chan": axes.get("FREQ", 1),
            "n_stokes": axes.get("STOKES", 1), "n_antenna": int(tables["AIPS AN"].get("NAXIS2", 0)),
            "freq_hz": float(primary.get("CRVAL4", 0.0) if str(primary.get("CTYPE4", "")).strip() == "FREQ" else 0.0)}


def check_fitsidi(path, role: str = "FITS-IDI input") -> Dict:
    """Check a FITS-IDI file before it is imported; return a summary. One-line errors."""
    hdus = _hdus(str(path), role)
    tables = {}
    for h, _, _ in hdus[1:]:
        tables.setdefault(str(h.get("EXTNAME", "")).strip(), []).append(h)
    if "UV_DATA" not in tables:
        raise InputError(f"{role} '{path}' has no UV_DATA table; it holds no visibilities "
                         "(a FITS-IDI file without data, or not FITS-IDI)")
    for name in ("ARRAY_GEOMETRY", "ANTENNA"):
        if name not in tables:
            raise InputError(f"{role} '{path}' has no {name} table; the stations are unknown: "
                             "give the complete correlator output")
    if "FREQUENCY" not in tables:
        raise InputError(f"{role} '{path}' has no FREQUENCY table; the frequency setup is unknown")
    n_band = max(int(h.get("NO_BAND", 1)) for hs in tables.values() for h in hs)
    if n_band > 1:
        raise InputError(
            f"{role} '{path}' holds {n_band} IFs (NO_BAND); hitops calibrate takes one "
            "spectral window per band: import it with CASA importfitsidi, combine or split the "
            "IFs (mstransform combinespws=True, or split spw=...) and give the Measurement Set")
    freq_rows = sum(int(h.get("NAXIS2", 0)) for h in tables["FREQUENCY"])
    if freq_rows > 1:
        raise InputError(f"{role} '{path}' holds {freq_rows} frequency setups (FREQUENCY "
                         "rows); give one setup per band (split it after CASA importfitsidi)")
    rows = sum(int(h.get("NAXIS2", 0)) for h in tables["UV_DATA"])
    if rows == 0:
        raise InputError(f"{role} '{path}' holds no visibilities (UV_DATA has no rows)")
    return {"rows": rows, "n_antenna": sum(int(h.get("NAXIS2", 0)) for h in tables["ANTENNA"])}


# ---------------------------------------------------------------- scans

def assign_scans(ms: str, gap_integrations: float = SCAN_GAP_INTEGRATIONS) -> Dict:
    """SCAN_NUMBER := a new scan at every time gap longer than ``gap_integrations`` integrations.

    The integration is the median INTERVAL (or the median step between distinct
    times when INTERVAL is 0).  Scans CASA already distinguished stay separate.
    Returns {"n_scans", "scans_added", "gap_s"}.
    """
    from casacore import tables as pt

    with pt.table(ms, readonly=False, ack=False) as t:
        if t.nrows() == 0:
            return {"n_scans": 0, "scans_added": 0, "gap_s": 0.0}
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
    return {"n_scans": n_after, "scans_added": max(0, n_after - n_before), "gap_s": gap_s}


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
    the set with :mod:`hitops.io.ms_create` (about 4x faster than CASA and no
    casatasks start-up; station codes in ANTENNA::NAME, scans from the AIPS NX
    table), and hands anything else to CASA ``importuvfits``; ``casa`` always
    uses CASA.  tests/test_convert.py checks that both give the same sets.
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
    stamp = _source_stamp(path)
    partial = dest.with_name(f".{dest.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    started = time.perf_counter()
    log.info("converting %s (%s, %d rows) into %s", path, fmt, summary["rows"], dest)
    try:
        tool = ""
        if fmt == "uvfits" and reader == "auto":
            try:
                _import_uvfits_direct(path, _hdus(path, role), str(partial))
                tool = "hitops.io.convert (numpy reader + ms_create)"
            except _NeedsCasa as why:
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
        _single_setup(str(partial), path, role)
        scans = assign_scans(str(partial), gap_integrations)
        seconds = time.perf_counter() - started
        record = {**stamp, "format": fmt, "tool": tool, "ms": str(dest), "seconds": seconds,
                  "n_scans": scans["n_scans"], "scans_added": scans["scans_added"],
                  "scan_gap_s": scans["gap_s"], "rows": summary["rows"]}
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
    except ExternalToolError as err:
        shutil.rmtree(partial, ignore_errors=True)
        raise InputError(f"{role} '{path}' could not be converted ({tool}): "
                         f"{str(err).splitlines()[0]}; check the file with the tool that "
                         "wrote it") from err
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    log.info("%s -> %s in %.2f s (%s); %d scans (%d added at time gaps > %.1f s)", path, dest,
             seconds, tool, scans["n_scans"], scans["scans_added"], scans["gap_s"])
    return Conversion(source=path, format=fmt, ms=str(dest), converted=True, seconds=seconds,
                      n_scans=scans["n_scans"], scans_added=scans["scans_added"],
                      scan_gap_s=scans["gap_s"], tool=tool)


def _single_setup(ms: str, path: str, role: str) -> None:
    """After the import: one spectral window and one field, or a one-line error."""
    from casacore import tables as pt

    with pt.table(f"{ms}::SPECTRAL_WINDOW", ack=False) as t:
        n_spw = t.nrows()
    if n_spw > 1:
        raise InputError(f"{role} '{path}' holds {n_spw} spectral windows (frequency setups or "
                         "IFs); hitops calibrate takes one per band: split them first")


def prepare_pair(ref, target, workdir: Optional[str] = None):
    """(ref MS, target MS, [Conversion, Conversion]) for calibrate's REF and TARGET."""
    ref_c = ensure_ms(ref, "REF (reference band)", workdir)
    tgt_c = ensure_ms(target, "TARGET (target band)", workdir)
    if ref_c.format != "ms" and os.path.realpath(ref_c.ms) == os.path.realpath(tgt_c.ms):
        raise InputError(f"REF '{ref}' and TARGET '{target}' convert to the same set "
                         f"'{ref_c.ms}'; give files with different names or the same file once")
    return ref_c.ms, tgt_c.ms, [ref_c, tgt_c]


# ---------------------------------------------------------------- hitops calibrate hooks

#: conversions done or reused in this process, by the real path of the Measurement Set
_SEEN: Dict[str, Conversion] = {}


def check_output_file(path, overwrite: bool, option: str) -> None:
    """Before anything is written: an existing output file needs ``--overwrite``."""
    if not path:
        return
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{option} '{path}' is a directory; give a file name")
    if p.exists() and not overwrite:
        raise OutputExistsError(f"{option} '{path}' exists; pass --overwrite to replace it or "
                                f"give another {option} path (nothing was written)")
    parent = p.resolve().parent
    if parent.exists() and not os.access(parent, os.W_OK):
        raise InputError(f"{option} '{path}': its directory {parent} is not writable; give a "
                         "writable path")


def prepare_inputs(ref, target, workdir: Optional[str] = None,
                   export_uvfits: Optional[str] = None, overwrite: bool = False,
                   caltable: Optional[str] = None, tracker: Optional[str] = None):
    """calibrate's first step for issue 13: check the outputs, convert non-MS inputs.

    Returns (ref MS, target MS).  The --export-uvfits and --caltable paths are
    checked before any conversion or calibration, so a refused run changes
    nothing; a caltable needs the antenna tracker (``tracker``), the only one
    with per-antenna solutions.
    """
    _SEEN.clear()           # this run's conversions only (a process may run calibrate often)
    check_output_file(export_uvfits, overwrite, "--export-uvfits")
    if caltable:
        if tracker is not None and tracker != "antenna":
            raise InputError(f"--caltable '{caltable}' needs --tracker antenna: a calibration "
                             "table holds one phase per antenna, and only the antenna tracker "
                             f"solves per antenna (--tracker {tracker} works per baseline)")
        if Path(caltable).exists() and not overwrite:
            raise OutputExistsError(f"--caltable '{caltable}' exists; pass --overwrite to "
                                    "replace it or give another --caltable path (nothing was "
                                    "written)")
    for given in (ref, target):
        for option, out in (("--export-uvfits", export_uvfits), ("--caltable", caltable)):
            if out and Path(given).exists() and \
                    os.path.realpath(given) == os.path.realpath(out):
                raise InputError(f"{option} '{out}' is an input; give another path (inputs "
                                 "are never written)")
    ref_ms, target_ms, conversions = prepare_pair(ref, target, workdir)
    for c in conversions:
        if c.format != "ms":
            _SEEN[os.path.realpath(c.ms)] = c
    return ref_ms, target_ms


def finish_report(report: Dict, opts, ref_ms: str, target_ms: str, outputs: Dict[str, str],
                  methods: List[str]) -> bool:
    """calibrate's last step for issue 13: conversions in the report, then --export-uvfits.

    Returns True when ``report`` changed (the caller writes it again).
    """
    changed = False
    conversions = []
    for role, ms in (("ref", ref_ms), ("target", target_ms)):
        c = _SEEN.get(os.path.realpath(ms))
        if c is not None:
            conversions.append({"band": role, **c.as_dict()})
    if conversions:
        report["conversions"] = conversions
        changed = True
    path = getattr(opts, "export_uvfits", None)
    if path:
        from .uvfits import export_uvfits

        column = outputs[methods[0]]
        report["export_uvfits"] = export_uvfits(
            target_ms, path, column, overwrite=bool(opts.overwrite),
            role="target-band Measurement Set",
            history=[f"hitops calibrate --method {','.join(methods)} --tracker {opts.tracker}",
                     f"reference band: {Path(ref_ms).name}"])
        changed = True
    return changed


# ---------------------------------------------------------------- direct UVFITS reader

#: AIPS STOKES axis value -> correlation name (the ones hitops calibrate transfers)
_AIPS_CORR = {-1: "RR", -2: "LL", -3: "RL", -4: "LR", -5: "XX", -6: "YY", -7: "XY", -8: "YX"}
_FITS_DTYPES = {8: "u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
#: binary-table TFORM codes read here (P/Q heap columns and bit arrays are left to CASA)
_TFORM = {"A": "S", "L": "S1", "B": "u1", "I": ">i2", "J": ">i4", "K": ">i8", "E": ">f4",
          "D": ">f8", "C": ">c8", "M": ">c16"}
#: telescope names CASA's Observatories table knows; others are written as VLBA (CASA
#: listobs refuses unknown names, e.g. 'EHT')
_CASA_TELESCOPES = {"VLBA", "ALMA", "VLA", "EVLA", "SMA", "ATCA", "MEERKAT", "GMRT", "WSRT",
                    "NOEMA", "IRAM PDB", "KVN", "JCMT", "APEX", "LOFAR", "NRO"}


class _NeedsCasa(Exception):
    """The file uses a UVFITS feature the direct reader leaves to CASA importuvfits."""


def _read_bintable(path: str, header: Dict, offset: int) -> Dict[str, np.ndarray]:
    """Columns of a FITS binary table (fixed-width columns only)."""
    n_row = int(header.get("NAXIS2", 0))
    width = int(header.get("NAXIS1", 0))
    fields = []
    pos = 0
    for k in range(1, int(header.get("TFIELDS", 0)) + 1):
        name = str(header.get(f"TTYPE{k}", f"col{k}")).strip()
        form = str(header.get(f"TFORM{k}", "")).strip()
        digits = "".join(ch for ch in form if ch.isdigit())
        code = form[len(digits):len(digits) + 1]
        count = int(digits) if digits else 1
        if code not in _TFORM:
            raise _NeedsCasa(f"table column {name} has format {form}")
        if code == "A":
            dtype, size = f"S{count}", count
        else:
            base = np.dtype(_TFORM[code])
            dtype, size = ((base, (count,)) if count != 1 else base), base.itemsize * count
        if count:
            fields.append((name, pos, dtype))
        pos += size
    if pos != width:
        raise _NeedsCasa(f"binary table width {width} != {pos}")
    dt = np.dtype({"names": [f[0] for f in fields], "formats": [f[2] for f in fields],
                   "offsets": [f[1] for f in fields], "itemsize": width})
    raw = np.fromfile(path, dtype=dt, count=n_row, offset=offset)
    return {name: raw[name] for name in dt.names}


def _read_uvfits_direct(path: str, hdus) -> Dict:
    """Everything create_ms needs from a plain UVFITS file; _NeedsCasa for anything else.

    Plain: one source, one IF, one channel, circular or linear correlations,
    BASELINE (not ANTENNA1/2) and DATE parameters, UTC times, weights present.
    """
    h = hdus[0][0]
    naxis = int(h["NAXIS"])
    axes = []
    for k in range(2, naxis + 1):
        axes.append((str(h.get(f"CTYPE{k}", "")).strip(), int(h[f"NAXIS{k}"]),
                     float(h.get(f"CRVAL{k}", 0.0)), float(h.get(f"CDELT{k}", 1.0)),
                     float(h.get(f"CRPIX{k}", 1.0))))
    names = [a[0] for a in axes]
    # an axis of length 1 without a name (EHT-HOPS files leave CTYPE5 out) is harmless
    known = {"COMPLEX", "STOKES", "FREQ", "IF", "RA", "DEC"}
    if any(n not in known and not (n == "" and a[1] == 1) for n, a in zip(names, axes)):
        raise _NeedsCasa(f"axes {names}")
    size = {a[0]: a[1] for a in axes}
    if size.get("COMPLEX") != 3 or size.get("FREQ", 1) != 1 or size.get("IF", 1) != 1:
        raise _NeedsCasa(f"axis lengths {size}")
    stokes_axis = next((a for a in axes if a[0] == "STOKES"), ("STOKES", 1, -1.0, -1.0, 1.0))
    codes = [int(round(stokes_axis[2] + (i + 1 - stokes_axis[4]) * stokes_axis[3]))
             for i in range(stokes_axis[1])]
    if any(c not in _AIPS_CORR for c in codes):
        raise _NeedsCasa(f"Stokes codes {codes}")
    corr = [_AIPS_CORR[c] for c in codes]
    if len(set(corr)) != len(corr) or not set(corr) <= {"RR", "LL", "RL", "LR"} and \
            not set(corr) <= {"XX", "YY", "XY", "YX"}:
        raise _NeedsCasa(f"correlations {corr}")

    pcount = int(h.get("PCOUNT", 0))
    ptypes = [str(h.get(f"PTYPE{k}", "")).strip().upper() for k in range(1, pcount + 1)]
    gcount = int(h["GCOUNT"])
    bitpix = int(h["BITPIX"])
    if bitpix not in (-32, -64):
        raise _NeedsCasa(f"BITPIX {bitpix}")
    n_cube = int(np.prod([a[1] for a in axes]))
    raw = np.memmap(path, dtype=_FITS_DTYPES[bitpix], mode="r", offset=hdus[0][1],
                    shape=(gcount, pcount + n_cube))

    def par(k: int) -> np.ndarray:
        scale = float(h.get(f"PSCAL{k + 1}", 1.0))
        zero = float(h.get(f"PZERO{k + 1}", 0.0))
        return raw[:, k].astype(np.float64) * scale + zero

    def find(prefix: str) -> List[int]:
        return [k for k, p in enumerate(ptypes) if p == prefix or p.startswith(prefix + "-")
                or (prefix in ("UU", "VV", "WW") and p.startswith(prefix))]

    for needed in ("UU", "VV", "WW", "BASELINE", "DATE"):
        if not find(needed):
            raise _NeedsCasa(f"no {needed} parameter ({ptypes})")
    for optional in ("SOURCE", "FREQSEL"):
        for k in find(optional):
            if np.unique(raw[:, k]).size > 1:
                raise _NeedsCasa(f"several {optional} values")
    uvw = np.stack([par(find(a)[0]) for a in ("UU", "VV", "WW")], axis=1) * 299792458.0
    jd = sum(par(k) for k in find("DATE"))
    baseline = par(find("BASELINE")[0])
    whole = np.floor(baseline + 1e-3)
    if np.any(np.abs(baseline - whole) > 1e-3):
        raise _NeedsCasa("sub-arrays in BASELINE")
    ant1_num = (whole // 256).astype(np.int64)
    ant2_num = (whole % 256).astype(np.int64)
    inttim = par(find("INTTIM")[0]) if find("INTTIM") else None

    tables = {str(t.get("EXTNAME", "")).strip(): (t, off) for t, off, _ in hdus[1:]}
    an_h, an_off = tables["AIPS AN"]
    timsys = str(an_h.get("TIMSYS", an_h.get("TIMESYS", "UTC"))).strip().upper()
    if timsys not in ("UTC", ""):
        raise _NeedsCasa(f"time system {timsys}")
    an = _read_bintable(path, an_h, an_off)
    anname = [s.decode("ascii", "replace").split("\0")[0].strip() for s in an["ANNAME"]]
    nosta = np.asarray(an["NOSTA"], np.int64)
    positions = np.asarray(an["STABXYZ"], np.float64).reshape(-1, 3) + np.array(
        [float(an_h.get(k, 0.0)) for k in ("ARRAYX", "ARRAYY", "ARRAYZ")])
    diameters = (np.asarray(an["DIAMETER"], np.float64) if "DIAMETER" in an
                 else np.zeros(len(anname)))
    lookup = np.full(max(int(nosta.max()), int(ant1_num.max()), int(ant2_num.max())) + 1, -1)
    lookup[nosta] = np.arange(nosta.size)
    ant1, ant2 = lookup[ant1_num], lookup[ant2_num]
    if np.any(ant1 < 0) or np.any(ant2 < 0):
        missing = sorted(set(ant1_num[ant1 < 0].tolist()) | set(ant2_num[ant2 < 0].tolist()))
        raise InputError(f"UVFITS '{path}' has visibilities of antenna number(s) {missing} "
                         "that its antenna table (AIPS AN) does not list; the file is "
                         "inconsistent: write it again with its AN table")

    freq_axis = next((a for a in axes if a[0] == "FREQ"), None)
    if freq_axis is None:
        raise _NeedsCasa("no FREQ axis")
    freq = freq_axis[2] + (1 - freq_axis[4]) * freq_axis[3]
    bandwidth = abs(freq_axis[3])
    if "AIPS FQ" in tables:
        fq = _read_bintable(path, *tables["AIPS FQ"])
        if "IF FREQ" in fq:
            freq += float(np.ravel(fq["IF FREQ"])[0])
        for key in ("TOTAL BANDWIDTH", "CH WIDTH"):
            if key in fq and float(np.ravel(fq[key])[0]) > 0:
                bandwidth = abs(float(np.ravel(fq[key])[0]))
                break
    # source: the SU table (one row) or the header
    src_name = str(h.get("OBJECT", "")).strip() or "SOURCE"
    ra_deg = h.get("OBSRA")
    dec_deg = h.get("OBSDEC")
    if "AIPS SU" in tables:
        su = _read_bintable(path, *tables["AIPS SU"])
        if len(su.get("SOURCE", [])) > 1:
            raise _NeedsCasa("several sources")
        if len(su.get("SOURCE", [])) == 1:
            src_name = su["SOURCE"][0].decode("ascii", "replace").strip() or src_name
            ra_deg, dec_deg = float(su["RAEPO"][0]), float(su["DECEPO"][0])
    if ra_deg is None or dec_deg is None:
        ra_ax = next((a for a in axes if a[0] == "RA"), None)
        dec_ax = next((a for a in axes if a[0] == "DEC"), None)
        if ra_ax is None or dec_ax is None:
            raise _NeedsCasa("no source position")
        ra_deg, dec_deg = ra_ax[2], dec_ax[2]

    # visibilities: reorder the cube to (row, stokes, complex) whatever the axis order
    shape = [a[1] for a in axes][::-1]
    cube = raw[:, pcount:].reshape([gcount] + shape)
    order = [names[::-1].index("STOKES") + 1 if "STOKES" in names else None,
             names[::-1].index("COMPLEX") + 1]
    if order[0] is None:
        raise _NeedsCasa("no STOKES axis")
    cube = np.moveaxis(cube, order, [-2, -1]).reshape(gcount, len(corr), 3).astype(np.float32)
    scale, zero = float(h.get("BSCALE", 1.0)), float(h.get("BZERO", 0.0))
    if scale != 1.0 or zero != 0.0:
        cube = cube * scale + zero
    # correlations in the Measurement Set's usual order (RR, RL, LR, LL), as CASA writes them
    from .ms_create import CORR_CODES

    by_code = sorted(range(len(corr)), key=lambda k: CORR_CODES[corr[k]])
    corr = [corr[k] for k in by_code]
    cube = cube[:, by_code, :]
    weight = cube[:, :, 2]
    data = (cube[:, :, 0] + 1j * cube[:, :, 1]).astype(np.complex64)
    flag = ~(weight > 0) | ~np.isfinite(data)
    weight_abs = np.where(np.isnan(weight), 0.0, np.abs(weight))   # inf stays, as CASA keeps it
    with np.errstate(divide="ignore"):
        sigma = np.where(weight_abs > 0, 1.0 / np.sqrt(weight_abs), 0.0)
    time_s = (jd - 2400000.5) * 86400.0
    telescope = str(h.get("TELESCOP", "VLBA")).strip()
    return {
        "names": anname, "positions": positions, "diameters": diameters,
        "freq": float(freq), "bandwidth": float(bandwidth), "corr": corr,
        "field": (src_name, np.radians(float(ra_deg)), np.radians(float(dec_deg))),
        "telescope": telescope if telescope.upper() in _CASA_TELESCOPES else "VLBA",
        "main": {"TIME": time_s, "ANTENNA1": ant1, "ANTENNA2": ant2, "UVW": uvw,
                 "DATA": data, "FLAG": flag, "WEIGHT": weight_abs.astype(np.float32),
                 "SIGMA": sigma.astype(np.float32),
                 **({"INTERVAL": inttim, "EXPOSURE": inttim} if inttim is not None else {})},
        "nx": _read_bintable(path, *tables["AIPS NX"]) if "AIPS NX" in tables else None,
    }


def _scan_from_nx(nx: Optional[Dict], n_row: int) -> np.ndarray:
    """SCAN_NUMBER per row from an AIPS NX table's START VIS / END VIS (1 when absent)."""
    scan = np.ones(n_row, np.int32)
    if not nx or "START VIS" not in nx or "END VIS" not in nx:
        return scan
    for k, (a, b) in enumerate(zip(np.ravel(nx["START VIS"]), np.ravel(nx["END VIS"])), start=1):
        scan[max(int(a) - 1, 0):min(int(b), n_row)] = k
    return scan


def _import_uvfits_direct(path: str, hdus, out: str) -> None:
    """Write the Measurement Set ``out`` from a plain UVFITS file (hitops.io.ms_create)."""
    from .ms_create import ArrayLayout, Band, Field, create_ms

    d = _read_uvfits_direct(path, hdus)
    main = d["main"]
    main["SCAN_NUMBER"] = _scan_from_nx(d["nx"], main["TIME"].size)
    names = d["names"]
    create_ms(out, ArrayLayout(names, names, d["positions"], d["diameters"]),
              Band(d["freq"], d["bandwidth"], tuple(d["corr"])), Field(*d["field"]), main,
              telescope=d["telescope"], overwrite=True)


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
