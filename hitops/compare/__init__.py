"""Image-plane comparison of calibration methods: fractional peak-flux recovery.

The fractional peak-flux recovery of an image is the fitted peak divided by
the true peak of the source (Rioja et al. 2023; the FPT paper's Results):
a perfectly calibrated point source gives 1, phase errors that decorrelate
the visibilities give less.  Its uncertainty is the imfit peak error divided
by the input peak, combined in quadrature with the input's own relative error.
"""

from .table import PAPER, compare, recovery  # noqa: F401
