"""``--calibrator-field``: source-frequency phase referencing after the transfer.

* :mod:`.step`: the step as calibrate runs it (checks, the calibrator's model, the order
  of the work per window and staged column);
* :mod:`.passes`: the passes over the target set chunk by chunk (the run's rows per
  chunk), and the per-scan sums kept between chunks;
* :mod:`.solve`: the calibrator's side: each scan's integer, antenna terms;
* :mod:`.apply`: the target's side: the interpolated terms removed (through
  hitops/kernels/antenna_terms.py), each target scan's integer found and removed (or
  its rows flagged);
* :mod:`.bridge`: the reference wrap count carried across scan and field switches (one-
  channel windows, where there is no delay to find a scan's integer from);
* :mod:`.report`: the per-antenna report and the log's summary line.

What the step reads of a band by row number (a Measurement Set v2's main table, or a
processing set's groups and the run's staged data groups) is
:mod:`hitops.calibrate.set_rows`.

The kernels are in :mod:`hitops.kernels.phase_ref`.
"""

from .step import check_calibrator_field, phase_reference, settle_n0_warnings

__all__ = ["check_calibrator_field", "phase_reference", "settle_n0_warnings"]
