"""Which options each way of running ``hitops calibrate`` accepts, and the one place that refuses the rest.

A run is in one of three modes, decided by the options alone:

* ``visibilities``: the reference band's wraps tracked on REF_MS's visibilities (the
  paper's FPT; every tracker, the n0 step);
* ``table``: ``--reference-table``, the reference band's antenna phases from a CASA
  calibration table solved on REF_MS (:mod:`hitops.calibrate.from_table`);
* ``calibrator``: ``--calibrator-field``, the visibility path followed by source-frequency
  phase referencing on a calibrator (:mod:`hitops.calibrate.phaseref`).

:data:`REFUSED` declares, per mode, every option (or option value) the mode does not
accept and why; :func:`check_options` is the only function that refuses options, before
any set is opened, so a refused run changes nothing.  Checks that need a set (columns,
fields, tables) stay with the stage that reads it.  docs/calibrate.md, "Modes", shows the
same table.  When either band is an MSv4 processing set (what the path holds, not an
option), :data:`REFUSED_ON_PROCESSING_SETS` is checked first: what that backend does not
run yet (docs/msv4.md).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Tuple

from ..errors import InputError
from ..tracking.options import check_options as check_tracking_numbers


class Mode(enum.Enum):
    VISIBILITIES = "visibilities"
    TABLE = "table"
    CALIBRATOR = "calibrator"


def mode_of(opts) -> Mode:
    """The run's mode (a table wins: with a calibrator too, the table mode refuses it)."""
    if opts.input.reference_table:
        return Mode.TABLE
    if opts.input.calibrator_field:
        return Mode.CALIBRATOR
    return Mode.VISIBILITIES


def _n0_step(opts) -> bool:
    return bool(opts.n0.offset_model or opts.n0.offset_reference_column)


def _n0_flag(opts) -> str:
    return "--offset-model" if opts.n0.offset_model else "--offset-reference-column"


def _table(opts) -> str:
    return f"--reference-table {opts.input.reference_table}"


def _replaced_by_table(flag: str, opts) -> str:
    return (f"{flag} with {_table(opts)}: the table's solutions replace REF_MS's visibilities "
            "(their wraps counted by hitops.solutions, each target channel at R_k = nu_k / "
            f"nu_ref); drop {flag}")


@dataclass(frozen=True)
class Refused:
    """One option (or value) a mode does not accept: when it is given, and the line that
    says why and what to do."""

    option: str                                  # the flag, as the docs' table names it
    given: Callable[[object, List[str]], bool]   # (options, methods) -> refused?
    why: Callable[[object, List[str]], str]      # (options, methods) -> the one line


#: a table of antenna gains needs per-antenna solutions (the table mode has them already)
_CALTABLE_NEEDS_ANTENNA = Refused(
    "--caltable without --tracker antenna",
    lambda o, m: bool(o.output.caltable) and o.tracking.tracker != "antenna",
    lambda o, m: f"--caltable '{o.output.caltable}' needs --tracker antenna: a calibration "
                 "table holds one phase per antenna, and only the antenna tracker solves per "
                 f"antenna (--tracker {o.tracking.tracker} works per baseline)")

#: the calibrator's model column means nothing without a calibrator
_MODEL_NEEDS_CALIBRATOR = Refused(
    "--calibrator-model-column without --calibrator-field",
    lambda o, m: bool(o.input.calibrator_model_column) and not o.input.calibrator_field,
    lambda o, m: f"--calibrator-model-column {o.input.calibrator_model_column} is the model of "
                 "--calibrator-field's calibrator: give --calibrator-field NAME too, or drop it")

#: what each mode refuses, checked in this order (the first that applies is reported)
REFUSED: Dict[Mode, Tuple[Refused, ...]] = {
    Mode.VISIBILITIES: (
        _CALTABLE_NEEDS_ANTENNA,
        _MODEL_NEEDS_CALIBRATOR,
    ),
    Mode.TABLE: (
        Refused("--method cwu", lambda o, m: "cwu" in m,
                lambda o, m: f"--method cwu with {_table(o)}: on the table's wrap counts CWU "
                             "equals PWC (rewrapping cancels the target's unwrap); use --method "
                             "pwc (or pwc,cfpt to compare with the uncounted transfer)"),
        Refused("the n0 step without --method pwc",
                lambda o, m: _n0_step(o) and "pwc" not in m,
                lambda o, m: f"{_n0_flag(o)} with {_table(o)} and --method {','.join(m)}: the "
                             "n0 step solves the integers of the counted transfer; add pwc to "
                             "--method"),
        _MODEL_NEEDS_CALIBRATOR,
        Refused("--calibrator-field", lambda o, m: bool(o.input.calibrator_field),
                lambda o, m: f"--calibrator-field {o.input.calibrator_field} with {_table(o)}: "
                             "the calibrator step works on the visibility path's per-baseline "
                             "counts; run it without --reference-table, or solve the "
                             "calibrator's scans of the written column in CASA (fringefit "
                             "field=..., then applycal to the target)"),
        Refused("--ref-model-column", lambda o, m: bool(o.input.ref_model_column),
                lambda o, m: _replaced_by_table("--ref-model-column", o)),
        Refused("--ratio", lambda o, m: o.input.ratio is not None,
                lambda o, m: _replaced_by_table("--ratio", o)),
        Refused("--average-channels", lambda o, m: bool(o.input.average_channels),
                lambda o, m: _replaced_by_table("--average-channels", o)),
        Refused("--scheduler on a Measurement Set v2 target",
                lambda o, m: bool(o.run.scheduler) and not _is_store(o.target_ms),
                lambda o, m: f"--scheduler {o.run.scheduler} with {_table(o)} and the "
                             f"Measurement Set v2 target {o.target_ms}: the table path "
                             "corrects a casacore table on this process's threads (it is not "
                             "written from several processes); drop --scheduler, or convert "
                             "the target to an MSv4 processing set, whose chunks the workers "
                             "correct and write (docs/msv4.md)"),
        Refused("--tracker other than count", lambda o, m: o.tracking.tracker != "count",
                lambda o, m: _replaced_by_table(f"--tracker {o.tracking.tracker}", o)),
    ),
    Mode.CALIBRATOR: (
        _CALTABLE_NEEDS_ANTENNA,
        # a tracker other than count is refused on one-channel target windows only, which
        # needs the sets: hitops/calibrate/phaseref/step.py:check_calibrator_field
        Refused("the n0 step", lambda o, m: _n0_step(o),
                lambda o, m: f"--calibrator-field {o.input.calibrator_field} replaces the n0 "
                             "offset step (each scan's integer is solved on the calibrator and "
                             "the target): drop --offset-model / --offset-reference-column"),
    ),
}


def _on_processing_set(option: str, why: str) -> Refused:
    """An option the MSv4 path does not take yet (its step reads or writes MSv2 only)."""
    return Refused(option, lambda o, m: bool(_option_value(o, option)),
                   lambda o, m: f"{option} {_option_value(o, option)} with an MSv4 processing "
                                f"set ({_processing_set_of(o)}): {why}")


def _option_value(opts, option: str):
    section, name = _PROCESSING_SET_OPTIONS[option]
    return getattr(getattr(opts, section), name)


def _is_store(path) -> bool:
    from ..io.msv4.store import is_processing_set   # reads zarr.json alone
    return is_processing_set(str(path))


def _processing_set_of(opts) -> str:
    return next((str(p) for p in (opts.target_ms, opts.ref_ms) if _is_store(p)), "")


#: where each option refused on processing sets lives in the option sections
_PROCESSING_SET_OPTIONS = {
    "--reference-table": ("input", "reference_table"),
    "--calibrator-field": ("input", "calibrator_field"),
    "--restore-flags": ("input", "restore_flags"),
    "--save-flags": ("output", "save_flags"),
    "--export-uvfits": ("output", "export_uvfits"),
    "--caltable": ("output", "caltable"),
}
#: what no mode takes when either band is a processing set (docs/msv4.md)
REFUSED_ON_PROCESSING_SETS: Tuple[Refused, ...] = (
    _on_processing_set("--restore-flags", "CASA flag versions belong to Measurement Sets v2; "
                       "a processing set's run starts from its data group's flags and leaves "
                       "them as they were"),
    _on_processing_set("--save-flags", "the run's flags are its data group's own (no CASA "
                       "flag version); drop --save-flags"),
)


def check_numbers(opts) -> None:
    """The numeric options (the schema has checked types and choices), in every mode."""
    ratio = opts.input.ratio
    if ratio is not None and not (float(ratio) > 0 and math.isfinite(float(ratio))):
        raise InputError(f"--ratio {ratio}: R = nu_target / nu_reference must be a positive "
                         "number (e.g. 2.6744 for 230/86 GHz); omit it to take R from the sets")
    if int(opts.n0.max_offset_wraps) < 0:
        raise InputError(f"--max-offset-wraps {opts.n0.max_offset_wraps} must be >= 0")
    if int(opts.run.chunk_rows) < 0:
        raise InputError(f"--chunk-rows {opts.run.chunk_rows} must be >= 1 (or 0: from "
                         "--memory-budget)")
    check_tracking_numbers(opts.tracking)
    tolerance = opts.input.time_tolerance
    if tolerance is not None and not float(tolerance) > 0:
        raise InputError(f"--time-tolerance {tolerance} must be a positive number of "
                         "seconds; omit it to use half the smallest INTERVAL")
    if not float(opts.run.lock_timeout) >= 0:
        raise InputError(f"--lock-timeout {opts.run.lock_timeout} must be >= 0 seconds")
    if not float(opts.run.verdict_interval) > 0:
        raise InputError(f"--verdict-interval {opts.run.verdict_interval} must be a positive "
                         "number of seconds (e.g. 60)")


def _check_pairs(opts, methods: List[str]) -> None:
    """Options that exclude each other, in every mode."""
    if opts.n0.offset_model and opts.n0.offset_reference_column:
        raise InputError(f"--offset-model {opts.n0.offset_model} and --offset-reference-column "
                         f"{opts.n0.offset_reference_column} both set the n0 offset step; "
                         "give one")
    if opts.output.output_column and len(methods) > 1:
        raise InputError(f"--output-column {opts.output.output_column} names one column but "
                         f"--method lists {len(methods)} methods; run one method at a time to "
                         "rename")


def check_options(opts, methods: List[str]) -> Mode:
    """Every option checked before anything is opened: numbers, pairs that exclude each
    other, then the run's mode's :data:`REFUSED`.  Returns the mode."""
    check_numbers(opts)
    _check_pairs(opts, methods)
    mode = mode_of(opts)
    on_processing_set = REFUSED_ON_PROCESSING_SETS if _processing_set_of(opts) else ()
    for refused in on_processing_set + REFUSED[mode]:
        if refused.given(opts, methods):
            raise InputError(refused.why(opts, methods))
    return mode
