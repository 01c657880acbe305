"""The robust trackers' resolved parameters for one group pair (part of the plan).

The numbers (half-windows, gaps, jump thresholds, chunk context) follow from
the options, the group's time step and, unless switched off, each station's
elevation (hitops/tracking/options.py, docs/tracking.md).
"""

from __future__ import annotations

import logging
import math
from dataclasses import fields
from typing import Optional

from ..geometry import station_sin_elevation
from ..tracking.grid import TrackGrid, grid_positions
from ..tracking.options import ANTENNA_TRACK_HALF_WINDOW, TrackingSetup, setup_tracking
from .inputs import CalibrateOptions

log = logging.getLogger("hitops.calibrate")

#: the options that tune the smooth and antenna trackers (a count run says which of them
#: it ignores: those not at the schema's default)
ROBUST_OPTIONS = ("half_window", "coherence_time", "snr", "max_gap", "jump_threshold",
                  "jump_window", "jump_action", "refant", "solve_half_window",
                  "no_elevation_scaling")


def tracking_setup(opts: CalibrateOptions, grid: TrackGrid, target_ms: str, antenna_names,
                   snr_from: str, target_meta=None) -> Optional[TrackingSetup]:
    """The TrackingSetup of ``--tracker smooth|antenna`` (None for count, which has no
    parameters); checks --refant.  ``target_meta``: the run's SetMetadata of the target
    set (its ANTENNA positions and phase centre for the elevations)."""
    tracking = opts.tracking
    if tracking.tracker == "count":
        defaults = {f.name: f.default for f in fields(tracking)}
        changed = [k for k in ROBUST_OPTIONS
                   if getattr(tracking, k) != defaults[k]
                   and not (defaults[k] is None and not getattr(tracking, k))]
        if changed:
            log.warning("--tracker count ignores %s (they tune --tracker smooth/antenna)",
                        ", ".join("--" + k.replace("_", "-") for k in changed))
        return None
    if opts.tracking.refant and opts.tracking.tracker != "antenna":
        log.warning("--refant is used by --tracker antenna only; ignored")
    _, dt = grid_positions(grid.times, grid.scans.scan_of_time)
    fixed = float(opts.tracking.snr) > 0 or int(opts.tracking.half_window) > 0
    sin_el = None
    if not opts.tracking.no_elevation_scaling:
        sin_el = station_sin_elevation(target_ms, grid.times, target_meta)
        if sin_el is None:
            log.info("no station geometry in %s (ANTENNA positions off the Earth's surface): "
                     "--coherence-time is used without elevation scaling", target_ms)
    setup = setup_tracking(tracking, dt, list(antenna_names), "fixed" if fixed else snr_from,
                           sin_elevation=sin_el)
    _log_setup(setup)
    return setup


def _log_setup(setup) -> None:
    if setup.tracker == "antenna":
        windows = f"{ANTENNA_TRACK_HALF_WINDOW} on antenna tracks"
    elif setup.half_window > 0:
        windows = setup.half_window
    else:
        windows = f"per sample <= {setup.max_half_window}"
    jumps = (f"window {setup.jump_window}, threshold {math.degrees(setup.jump_threshold):.1f} deg"
             if setup.jump_threshold > 0 else "off")
    solve = ""
    if setup.tracker == "antenna":
        solve = ("; solve half-window "
                 f"{setup.solve_half_window if setup.solve_half_window >= 0 else 'per time'}")
    log.info("tracker %s: dt %.4g s, t_c %.4g s%s, half-window %s (SNR %s), max gap %d, jumps %s "
             "(action %s)%s; context %d samples per chunk side", setup.tracker, setup.dt,
             setup.coherence_time,
             " (zenith, x sin(el)^(3/5) per station)" if setup.elevation_scaling else "",
             windows, f"{setup.snr:.3g}" if setup.snr > 0 else f"from {setup.snr_source}",
             setup.max_gap, jumps, setup.jump_action, solve, setup.context)
