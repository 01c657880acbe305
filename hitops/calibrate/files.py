"""The files around a ``hitops calibrate`` run: inputs that are no Measurement Sets, file outputs.

Issue 13 let ``hitops calibrate`` take UVFITS and FITS-IDI files and write
``--export-uvfits`` and ``--caltable`` files.  The conversions themselves are
:mod:`hitops.io.convert`'s job; what only calibrate decides lives here:

* :func:`prepare_inputs`, the run's first step: the output files are checked
  before anything is converted or calibrated (an existing file needs
  ``--overwrite``; no output may be an input), then REF and TARGET are
  converted (or reused) into Measurement Sets.  It returns the conversions as
  a :class:`PreparedInputs`, which the run hands to its report stage;
* :func:`record_conversions_and_export`, the run's last step: the conversions in the report
  (its :class:`~hitops.calibrate.run_report.AfterCommit`), then ``--export-uvfits``
  with calibrate's history lines.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List

from ..errors import InputError, OutputExistsError
from ..io.convert import Conversion, ensure_ms

if TYPE_CHECKING:
    from .run_report import AfterCommit


@dataclass(frozen=True)
class PreparedInputs:
    """REF and TARGET as Measurement Sets, and what was done to get each."""

    ref: Conversion
    target: Conversion

    @property
    def ref_ms(self) -> str:
        return self.ref.ms

    @property
    def target_ms(self) -> str:
        return self.target.ms

    def report_entries(self) -> List[Dict]:
        """The report's ``conversions``: one entry per band given as UVFITS or FITS-IDI."""
        return [{"band": band, **c.as_dict()}
                for band, c in (("ref", self.ref), ("target", self.target)) if c.format != "ms"]


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


def prepare_inputs(opts) -> PreparedInputs:
    """calibrate's first step: check the output files, convert the inputs that are no sets.

    The --export-uvfits and --caltable paths are checked before any conversion
    or calibration, so a refused run changes nothing (the options themselves were
    checked before: hitops/calibrate/modes.py).
    """
    output = opts.output
    ref, target, reference_table = opts.ref_ms, opts.target_ms, opts.input.reference_table
    check_output_file(output.export_uvfits, output.overwrite, "--export-uvfits")
    # a CASA table is a directory: only its existence is checked
    if output.caltable and Path(output.caltable).exists() and not output.overwrite:
        raise OutputExistsError(f"--caltable '{output.caltable}' exists; pass --overwrite to "
                                "replace it or give another --caltable path (nothing was "
                                "written)")
    for given in (ref, target) + ((reference_table,) if reference_table else ()):
        for option, out in (("--export-uvfits", output.export_uvfits),
                            ("--caltable", output.caltable)):
            if out and Path(given).exists() and \
                    os.path.realpath(given) == os.path.realpath(out):
                raise InputError(f"{option} '{out}' is an input; give another path (inputs "
                                 "are never written)")
    workdir = opts.input.workdir
    ref_c = ensure_ms(ref, "REF (reference band)", workdir)
    tgt_c = ensure_ms(target, "TARGET (target band)", workdir)
    if ref_c.format != "ms" and os.path.realpath(ref_c.ms) == os.path.realpath(tgt_c.ms):
        raise InputError(f"REF '{ref}' and TARGET '{target}' convert to the same set "
                         f"'{ref_c.ms}'; give files with different names or the same file once")
    return PreparedInputs(ref_c, tgt_c)


def history_lines(methods: List[str], tracker: str, ref_ms: str) -> List[str]:
    """The HISTORY lines calibrate adds to an exported UVFITS file: how it was made."""
    return [f"hitops calibrate --method {','.join(methods)} --tracker {tracker}",
            f"reference band: {Path(ref_ms).name}"]


def record_conversions_and_export(after: AfterCommit, opts, ref_ms: str, target_ms: str,
                  outputs: Dict[str, str], methods: List[str], inputs: PreparedInputs) -> None:
    """calibrate's last step: the conversions (``after.conversions``), then --export-uvfits
    (``after.export_uvfits``)."""
    from ..io.uvfits import export_uvfits

    conversions = inputs.report_entries()
    if conversions:
        after.conversions = conversions
    path = opts.output.export_uvfits
    if path:
        after.export_uvfits = export_uvfits(
            target_ms, path, outputs[methods[0]], overwrite=bool(opts.output.overwrite),
            role="target band",
            history=history_lines(methods, opts.tracking.tracker, ref_ms))
