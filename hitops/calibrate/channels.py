"""One ratio per target channel (issue 26): what a group pair's channels ask of the transfer.

The troposphere is an excess path, so target channel k needs R_k = nu_k / nu_ref
(docs/wideband.md).  The transfer keeps the pipeline's one phasor per cell, at the
target window's centre nu_0 with R_0 = nu_0 / nu_ref (the group's R), and adds a
delay psi / (2*pi*nu_ref) per cell, psi the reference phase with its counted turns
put back: channel k then gets exp(-i*R_0*psi) * exp(-2*pi*i*(nu_k - nu_0)*psi /
(2*pi*nu_ref)) = exp(-i*R_k*psi), the form of a CASA 'Fringe Jones' table.

The reference band's channels are reduced to one phase per row at nu_ref (its
window's centre) by a delay fit across them
(:func:`hitops.kernels.wideband.reference_phasors`), the target's to nu_0 the same
way when CWU needs its phase (or a one-channel n0 step); PWC and CFPT take the rows'
validity alone, and the n0 step runs across the target's channels
(hitops/calibrate/n0/, :meth:`ChannelPlan.offset_window`).  With ``--average-channels``,
or one channel on each side, there is no :class:`ChannelPlan` and the single-ratio path
runs as it always has.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..io import read as msio
from ..kernels import wideband
from .groups import GroupPair

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class ChannelPlan:
    """The frequencies one group pair's per-channel transfer works with (Hz)."""

    ref_chan_freq: np.ndarray     # (n_chan_ref,) the reference window's channels
    ref_freq: float               # what the reduced reference phase refers to (nu_ref)
    tgt_chan_freq: np.ndarray     # (n_chan,) the target window's channels
    tgt_centre: float             # nu_0: the target's reduced phase and the phasor refer here
    ratio: float                  # R_0 = nu_0 / nu_ref (the group's R)

    @property
    def chan_offset(self) -> np.ndarray:
        """nu_k - nu_0 of every target channel."""
        return self.tgt_chan_freq - self.tgt_centre

    @property
    def ratios(self) -> np.ndarray:
        """R_k of every target channel."""
        return self.tgt_chan_freq * (self.ratio / self.tgt_centre)

    @property
    def across_channels(self) -> bool:
        """The target window has several channels: the n0 step runs across them
        (hitops/calibrate/n0/), and the target's own reduction serves CWU alone."""
        return self.tgt_chan_freq.size > 1

    def offset_window(self, eps: float):
        """The n0 step's :class:`hitops.calibrate.n0.baseline.WindowRatios` (``eps``: the
        group's, R_0's fractional part), or None with one target channel."""
        from .n0.baseline import WindowRatios

        return WindowRatios(self.ratios, self.ratio, eps) if self.across_channels else None

    def as_report(self) -> dict:
        ratios = self.ratios
        return {"reference_frequency_hz": self.ref_freq, "target_centre_hz": self.tgt_centre,
                "n_chan_reference": int(self.ref_chan_freq.size),
                "n_chan_target": int(self.tgt_chan_freq.size),
                "ratio_min": float(ratios.min()), "ratio_max": float(ratios.max()),
                "reference_reduction": "delay fit across the channels, phase at the window "
                                       "centre" if self.ref_chan_freq.size > 1 else "one channel"}


def channel_plan(pair: GroupPair, ratio: float, average_channels: bool,
                 label: str = "") -> Optional[ChannelPlan]:
    """The pair's :class:`ChannelPlan`, or None when one ratio serves (one channel each side,
    or ``--average-channels``).  ``ratio``: the group's R (from the windows or --ratio),
    taken as the ratio at the target window's centre."""
    if average_channels:
        if max(pair.ref.n_chan, pair.tgt.n_chan) > 1:
            log.warning("%s--average-channels: one ratio for all channels of spectral window "
                        "%d; the path's phase slope across the window, 2*pi*(nu_k - nu_0)*L/c, "
                        "stays in the output (radians at a 2-GHz window's edge for a few cm of "
                        "path; docs/wideband.md)", f"{label}: " if label else "", pair.tgt.spw)
        return None
    if pair.ref.n_chan == 1 and pair.tgt.n_chan == 1:
        return None
    tgt_chan = np.asarray(pair.tgt.chan_freq, dtype=np.float64)
    plan = ChannelPlan(ref_chan_freq=np.asarray(pair.ref.chan_freq, dtype=np.float64),
                       ref_freq=pair.tgt.freq / ratio, tgt_chan_freq=tgt_chan,
                       tgt_centre=pair.tgt.freq, ratio=ratio)
    ratios = plan.ratios
    log.info("%sper-channel ratios: reference spectral window %d (%d channels) reduced to its "
             "phase at %.6g GHz by a delay fit; target spectral window %d: %d channels, R_k "
             "%.8g .. %.8g", f"{label}: " if label else "", pair.ref.spw, pair.ref.n_chan,
             plan.ref_freq / 1e9, pair.tgt.spw, tgt_chan.size, ratios.min(), ratios.max())
    return plan


def check_channel_counts(ms: str, role: str, column: str, ds, n_chan: int, spw: int) -> None:
    """The column's channel axis in dataset ``ds`` agrees with SPECTRAL_WINDOW::NUM_CHAN."""
    n_data = _data_channels(ms, column, ds)
    if n_data != n_chan:
        from ..errors import MeasurementSetError

        raise MeasurementSetError(
            f"{role} '{ms}': column {column} has {n_data} channel(s) but spectral window "
            f"{spw} has {n_chan} in the SPECTRAL_WINDOW table; the set is inconsistent: "
            "rewrite it (CASA mstransform) or take the window out (CASA split spw=...)")


def _data_channels(ms: str, column: str, ds) -> int:
    """Channels of ``column`` in a group's dataset (a dask-ms dataset, or the python-casacore
    reader of a one-group set, whose first row is the group's)."""
    if isinstance(ds, msio.StorageRows):
        return int(ds.cell_shape(column)[0])
    return int(ds[column].shape[1])


def reduce_rows(data: np.ndarray, good: np.ndarray, chan_freq: np.ndarray, at_freq: float):
    """(n_row, n_corr) complex64 visibility at ``at_freq`` and its validity, from
    (n_row, n_chan, n_corr) channels: the delay fit of :mod:`hitops.kernels.wideband`."""
    delay = wideband.row_delays(data, good, chan_freq)
    reduced, ok = wideband.reference_phasors(data, good, chan_freq, float(at_freq), delay)
    return reduced.astype(np.complex64), ok
