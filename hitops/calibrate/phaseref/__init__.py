"""``--calibrator-field``: source-frequency phase referencing after the transfer.

* :mod:`.step`: the step as calibrate runs it (checks, the solve per calibrator scan,
  the interpolation, the correction of the target's rows in the staged column);
* :mod:`.bridge`: the reference wrap count carried across scan and field switches;
* :mod:`.report`: the per-antenna report and the log's summary line.

The kernels are in :mod:`hitops.kernels.phase_ref`.
"""

from .step import check_calibrator_field, phase_reference, settle_n0_warnings

__all__ = ["check_calibrator_field", "phase_reference", "settle_n0_warnings"]
