"""Dual-band Measurement Set pairs with a known troposphere, for tests and benchmarks.

Not a simulator (that is ``hitops.simulate``): each antenna gets a smooth
random-walk phase at the reference band (plus a drift, so the baseline
phases wrap many times); the target band carries R times that phase plus a
constant per-baseline "source" phase; optional complex Gaussian noise.
Because every term is known, the tests can predict exactly what CFPT, PWC
and CWU must return.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np

from ..io.ms_create import ArrayLayout, Band, Field, create_ms

#: station names used by default (the paper's array codes)
DEFAULT_NAMES = ("AP", "SM", "PV", "GL", "PB", "KP", "KC", "KY")


@dataclass
class PairTruth:
    """What the synthetic pair was built from (per target row)."""

    ref_ms: Path
    target_ms: Path
    ratio: float
    ant1: np.ndarray             # target-band ANTENNA1 per target row
    ant2: np.ndarray
    time: np.ndarray
    scan: np.ndarray
    ref_phase_true: np.ndarray   # (n_row, n_corr) unwrapped reference-band phase of the baseline
    source_phase: np.ndarray     # (n_row, n_corr) target-band phase left after perfect FPT
    extra: Dict[str, np.ndarray] = field(default_factory=dict)


def wrap(phase):
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(phase) + np.pi) % (2 * np.pi) - np.pi


def make_pair(directory, *, n_ant: int = 4, n_time: int = 300, dt: float = 1.0,
              ratio: float = 230.0 / 86.0, ref_freq_hz: float = 86e9,
              corr_types: Sequence[str] = ("RR", "LL"), step_rad: float = 0.15,
              drift_rad: float = 0.05, sigma_ref: float = 0.0, sigma_target: float = 0.0,
              ref_amp: float = 1.1, target_amp: float = 1.0, n_scans: int = 1,
              ref_names: Optional[Sequence[str]] = None,
              target_names: Optional[Sequence[str]] = None,
              t0: float = 5.1e9, seed: int = 0, phase_offset_rad: float = 0.0,
              shuffle_ref: bool = False, shuffle_target: bool = False,
              time_order: bool = False,
              swap_ref_baselines: Sequence[int] = (), ref_time_shift: float = 0.0,
              ref_name: str = "ref.ms", target_name: str = "target.ms",
              ref_offset_scale: float = 0.3) -> PairTruth:
    """Write ``ref.ms`` and ``target.ms`` under ``directory``; return the truth.

    ``step_rad``: std of each antenna's per-sample random-walk step at the
    reference band (keep below ~1 so the Itoh condition holds);
    ``drift_rad``: per-sample linear drift per antenna (spread over antennas);
    ``sigma_ref``/``sigma_target``: std of each real/imaginary noise component;
    ``phase_offset_rad``: constant times (antenna number) added to each
    antenna phase at the reference band, so that baselines start at
    different wrap counts (n0 != 0);
    ``shuffle_ref``/``shuffle_target``: store the rows in random order;
    ``time_order``: store the rows of both bands sorted by time (as correlators
    write them) rather than baseline by baseline;
    ``swap_ref_baselines``: baseline indices whose reference rows are stored
    with the antenna order reversed (visibility conjugated, RL <-> LR);
    ``ref_time_shift``: seconds added to the reference TIME column;
    ``ref_offset_scale``: the reference band's constant per baseline and correlation
    is uniform in +-pi times this; it does not close (as source structure would not),
    and 0 makes the reference band purely antenna-based.
    The truth is given per target row, in the target's storage order.
    """
    rng = np.random.default_rng(seed)
    directory = Path(directory)
    ref_names = list(ref_names or DEFAULT_NAMES[:n_ant])
    target_names = list(target_names or ref_names)
    n_corr = len(corr_types)
    times = t0 + dt * np.arange(n_time)
    # troposphere per antenna: drift + random walk (float64, unwrapped)
    drift = drift_rad * np.linspace(-1.0, 1.0, n_ant)
    walk = np.cumsum(rng.normal(0.0, step_rad, (n_ant, n_time)), axis=1)
    ant_phase = walk + drift[:, None] * np.arange(n_time) + phase_offset_rad * np.arange(1, n_ant + 1)[:, None]
    # scans: equal slices of the track
    scan_of_time = 1 + (np.arange(n_time) * n_scans) // n_time

    a1, a2 = np.triu_indices(n_ant, 1)
    n_bl = a1.size
    ant1 = np.repeat(a1, n_time)
    ant2 = np.repeat(a2, n_time)
    time = np.tile(times, n_bl)
    scan = np.tile(scan_of_time, n_bl)
    t_idx = np.tile(np.arange(n_time), n_bl)
    bl_phase = ant_phase[ant1, t_idx] - ant_phase[ant2, t_idx]
    corr_offset = rng.uniform(-np.pi, np.pi, (n_bl, n_corr)) * ref_offset_scale
    ref_true = bl_phase[:, None] + np.repeat(corr_offset, n_time, axis=0)
    source = np.repeat(rng.uniform(-np.pi, np.pi, (n_bl, n_corr)), n_time, axis=0)
    n_row = time.size
    ref_vis = ref_amp * np.exp(1j * ref_true)
    tgt_vis = target_amp * np.exp(1j * (ratio * ref_true + source))
    if sigma_ref:
        ref_vis = ref_vis + rng.normal(0, sigma_ref, ref_vis.shape) + 1j * rng.normal(0, sigma_ref, ref_vis.shape)
    if sigma_target:
        tgt_vis = tgt_vis + rng.normal(0, sigma_target, tgt_vis.shape) + 1j * rng.normal(0, sigma_target, tgt_vis.shape)

    positions = np.array([[6.0e6 * np.cos(2 * np.pi * k / n_ant), 6.0e6 * np.sin(2 * np.pi * k / n_ant), 1.0e5 * k]
                          for k in range(n_ant)])
    fld = Field("SYNTH", 3.276, 0.2163)
    uvw = np.zeros((n_row, 3))
    bl_of_row = np.repeat(np.arange(n_bl), n_time)

    # reference band: optionally reversed antenna order on some baselines
    r_ant1, r_ant2, r_vis = ant1.copy(), ant2.copy(), ref_vis.copy()
    swap = np.isin(bl_of_row, np.asarray(swap_ref_baselines, dtype=np.int64))
    if swap.any():
        reverse = [list(corr_types).index(c[::-1]) for c in corr_types]
        r_ant1[swap], r_ant2[swap] = ant2[swap], ant1[swap]
        r_vis[swap] = np.conj(ref_vis[swap][:, reverse])
    stored = np.argsort(time, kind="stable") if time_order else np.arange(n_row)
    ref_order = rng.permutation(n_row) if shuffle_ref else stored
    tgt_order = rng.permutation(n_row) if shuffle_target else stored

    def columns(order, a1_, a2_, vis, shift=0.0):
        return dict(TIME=time[order] + shift, ANTENNA1=a1_[order], ANTENNA2=a2_[order],
                    UVW=uvw[order], SCAN_NUMBER=scan[order], INTERVAL=np.full(n_row, dt),
                    DATA=vis[order].astype(np.complex64))

    ref_ms = create_ms(directory / ref_name,
                       ArrayLayout(ref_names, ref_names, positions, np.full(n_ant, 12.0)),
                       Band(ref_freq_hz, 2e9, tuple(corr_types)), fld,
                       columns(ref_order, r_ant1, r_ant2, r_vis, ref_time_shift), overwrite=True)
    target_ms = create_ms(directory / target_name,
                          ArrayLayout(target_names, target_names, positions, np.full(n_ant, 12.0)),
                          Band(ref_freq_hz * ratio, 2e9, tuple(corr_types)), fld,
                          columns(tgt_order, ant1, ant2, tgt_vis), overwrite=True)
    o = tgt_order
    return PairTruth(ref_ms=ref_ms, target_ms=target_ms, ratio=ratio, ant1=ant1[o], ant2=ant2[o],
                     time=time[o], scan=scan[o], ref_phase_true=ref_true[o],
                     source_phase=source[o],
                     # the reference band's per-baseline constant, which does not close (like
                     # source structure): antenna-based FPT leaves R times it in the output
                     extra={"ref_offset": np.repeat(corr_offset, n_time, axis=0)[o]})


def add_column(ms, name: str, values: np.ndarray, like: str = "DATA") -> None:
    """Add main-table column ``name`` shaped like ``like`` and fill it (tests: CORRECTED_DATA)."""
    from casacore import tables as pt

    with pt.table(str(ms), readonly=False, ack=False) as t:
        desc = t.getcoldesc(like)
        desc["name"] = name
        t.addcols(pt.makecoldesc(name, desc))
        t.putcol(name, np.asarray(values).reshape((t.nrows(),) + t.getcell(like, 0).shape)
                 .astype(t.getcell(like, 0).dtype))


def expected_pwc_phase(truth: PairTruth, ratio: Optional[float] = None) -> np.ndarray:
    """PWC output phase predicted by the paper: source phase - 2*pi*eps*n0 (per scan).

    n(t) is the integer ambiguity of the wrapped reference phase
    (wrapped = true + 2*pi*n); PWC counts from n'(scan start) = 0, so the
    residual keeps -2*pi*eps*n0 with n0 = n at each series' first sample in its scan.
    """
    ratio = truth.ratio if ratio is None else ratio
    eps = ratio - np.floor(ratio)
    n_true = np.rint((wrap(truth.ref_phase_true) - truth.ref_phase_true) / (2 * np.pi)).astype(np.int64)
    n0 = np.zeros_like(n_true)
    key = (truth.ant1.astype(np.int64) * 1000 + truth.ant2) * 100000 + truth.scan
    order = np.lexsort((truth.time, key))
    first = {}
    for row in order:
        first.setdefault(int(key[row]), row)
    for row in range(key.size):
        n0[row] = n_true[first[int(key[row])]]
    return wrap(truth.source_phase - 2 * np.pi * eps * n0)
