"""CASA tasks run natively from the pip casatasks, with failures made loud.

CASA reports many failures only as SEVERE lines in its log (fringefit with
no valid reference antenna, gaincal with "Insufficient unflagged antennas"
in every interval) and returns normally, so a pipeline step that wrote no
calibration table looks like a success.  Every wrapper here:

* selects CASA's offline data configuration before importing casatasks
  (:func:`hitops.casa_env.ensure_casa_offline`);
* captures the log lines the task wrote and raises
  :class:`hitops.errors.ExternalToolError` on any SEVERE line, except the
  harmless TAI_UTC leap-second table message;
* checks that the promised output (calibration table, corrected column,
  fit component) exists and is not entirely flagged;
* returns plain Python floats/ints/strings, which Stimela's python flavour
  can serialise (numpy scalars cannot be).
"""

from .tasks import applycal, fringefit, gaincal, imfit  # noqa: F401
from .runner import run_task, severe_lines  # noqa: F401
