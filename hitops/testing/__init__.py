"""Test support shipped with the package (the tests and the benchmarks both use it).

:mod:`.pairs` writes dual-band Measurement Set pairs with a known troposphere
(:class:`~.pairs.PairSpec` in, :class:`~.pairs.PairTruth` out) and predicts
what the transfer must return; :mod:`.slips` counts a tracker's errors against
a known truth.  Nothing in ``hitops`` outside this package imports it.
"""

from .pairs import (DEFAULT_NAMES, PairSpec, PairTruth, Signal, Storage, Troposphere,
                    add_column, expected_pwc_phase, make_pair, wrap)
from .slips import count_slips, slip_errors

__all__ = ["DEFAULT_NAMES", "PairSpec", "PairTruth", "Signal", "Storage", "Troposphere",
           "add_column", "count_slips", "expected_pwc_phase", "make_pair", "slip_errors", "wrap"]
