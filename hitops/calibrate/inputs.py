"""Stage 2 of ``hitops calibrate`` (prepare): every column checked in both sets before a read.

:func:`check_inputs` turns the typed options into the run's :class:`Columns`
(what each band reads, what the n0 offset step compares with) and its output
columns, or raises a typed error naming the option and the remedy.  Nothing
here writes, so bad input leaves both sets as they were.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

from ..errors import InputError, OutputExistsError
from ..io import read as msio
from .band_index import INDEX_COLUMNS
from ..options import options_class
from .output import FLAG_BACKUP, STAGING_PREFIX

log = logging.getLogger("hitops.calibrate")

#: the typed options of ``hitops calibrate``: a frozen dataclass from hitops/schemas/calibrate.yml
CalibrateOptions = options_class("calibrate")

#: ``--offset-model point``: a point source at the phase centre (model phase 0 everywhere)
POINT_MODEL = "point"


def is_point_model(offset_model) -> bool:
    return bool(offset_model) and str(offset_model).strip().lower() == POINT_MODEL

#: the column each method writes unless --output-column renames it
DEFAULT_COLUMNS = {"pwc": "PWC_DATA", "cfpt": "CFPT_DATA", "cwu": "CWU_DATA"}


@dataclass(frozen=True)
class Columns:
    """The columns a run reads, and how the n0 offset step is given.

    ``ref``: reference data, FLAG and the optional reference model column;
    ``tgt``: target data, the input flags, and the offset step's column if any;
    ``snr``: SIGMA or WEIGHT read with the reference data (robust trackers);
    ``flag``: FLAG, or FLAG_HITOPS_BACKUP when --overwrite reruns start from it;
    ``offset``: what the n0 step compares with (a reference column, a model
    column or 'point'), None without the step; ``model``: the model column of
    ``--offset-model COLUMN``; ``snr_from``: 'sigma', 'weight' or 'data'.
    """

    ref_data: str
    ref_model: Optional[str]
    target_data: str
    flag: str
    offset: Optional[str]
    offset_is_model: bool
    model: Optional[str]
    ref: List[str] = field(default_factory=list)
    tgt: List[str] = field(default_factory=list)
    snr: List[str] = field(default_factory=list)
    snr_from: str = "data"


def parse_methods(method) -> List[str]:
    """The methods of ``--method`` (a list or a comma-separated string), checked."""
    items = method if isinstance(method, (list, tuple)) else str(method or "").split(",")
    methods = [m.strip().lower() for m in items if m and m.strip()]
    if not methods:
        raise InputError("--method is empty; give one or more of pwc, cfpt, cwu (e.g. --method pwc,cfpt)")
    for m in methods:
        if m not in DEFAULT_COLUMNS:
            raise InputError(f"--method: unknown method '{m}'; choose from pwc, cfpt, cwu")
    if len(set(methods)) != len(methods):
        raise InputError(f"--method lists a method twice: {','.join(methods)}")
    return methods


def output_columns(opts: CalibrateOptions, methods: List[str]) -> Dict[str, str]:
    """method -> the column it writes (one method with --output-column: hitops/calibrate/modes.py)."""
    return {m: (opts.output.output_column or DEFAULT_COLUMNS[m]) for m in methods}


def check_inputs(opts: CalibrateOptions, methods: List[str], ref_ms: str,
                 target_ms: str) -> Tuple[Dict[str, str], "Columns"]:
    """(outputs, :class:`Columns`) of a run, every column checked in both sets."""
    outputs = output_columns(opts, methods)
    present = set(msio.column_names(target_ms))
    # a rerun with --overwrite starts from the flags hitops found before its first run
    # (FLAG_HITOPS_BACKUP), so two identical runs give identical FLAG columns; a run that
    # was killed half-way through writing FLAG is repaired the same way
    # --restore-flags names the starting flags explicitly: FLAG holds them now
    flag_column = (FLAG_BACKUP if (opts.output.overwrite and FLAG_BACKUP in present
                                   and not opts.input.restore_flags) else "FLAG")
    if flag_column == FLAG_BACKUP:
        log.info("--overwrite: starting from %s (the flags before hitops first ran), not "
                 "from FLAG, so this run's flags replace the earlier run's", FLAG_BACKUP)
    offset_model = opts.n0.offset_model or None
    reference = opts.n0.offset_reference_column or None
    # --offset-model: 'point' or a model column of TARGET_MS (hitops/calibrate/n0/)
    model_column = offset_model if offset_model and not is_point_model(offset_model) else None
    ref_cols = [opts.input.ref_column, "FLAG"] + ([opts.input.ref_model_column] if opts.input.ref_model_column else [])
    tgt_cols = ([opts.input.target_column, flag_column] + ([reference] if reference else [])
                + ([model_column] if model_column else []))
    msio.require_columns(ref_ms, ref_cols + INDEX_COLUMNS, "reference-band Measurement Set",
                         "check --ref-column / --ref-model-column")
    msio.require_columns(target_ms, tgt_cols + INDEX_COLUMNS, "target-band Measurement Set",
                         "check --target-column / --offset-reference-column / --offset-model")
    protected = {opts.input.target_column, "FLAG", FLAG_BACKUP, "DATA", reference, model_column} - {None}
    for col in outputs.values():
        if col.startswith(STAGING_PREFIX):
            raise InputError(f"output column {col}: names starting with {STAGING_PREFIX} are "
                             "hitops's own unfinished columns; choose another --output-column")
        if col in protected:
            raise InputError(f"output column {col} of {target_ms} is an input or flag column; "
                             "choose another --output-column (e.g. PWC_DATA)")
        if col in present and not opts.output.overwrite:
            raise OutputExistsError(f"column {col} already exists in {target_ms}; pass "
                                    "--overwrite to replace it or --output-column to write "
                                    "another column")
    # the robust trackers take the per-sample SNR from SIGMA or WEIGHT where they are
    # informative (hitops/tracking/options.py): that column is read with the data
    snr_from = "data"
    if opts.tracking.tracker != "count" and not (float(opts.tracking.snr) > 0 or int(opts.tracking.half_window) > 0):
        from ..tracking.options import sigma_source
        snr_from = sigma_source(ref_ms)
    columns = Columns(ref_data=opts.input.ref_column, ref_model=opts.input.ref_model_column or None,
                      target_data=opts.input.target_column, flag=flag_column,
                      offset=reference or offset_model, offset_is_model=bool(offset_model),
                      model=model_column, ref=ref_cols, tgt=tgt_cols,
                      snr=[snr_from.upper()] if snr_from in ("sigma", "weight") else [],
                      snr_from=snr_from)
    return outputs, columns
