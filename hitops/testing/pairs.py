"""Dual-band Measurement Set pairs with a known troposphere, for tests and benchmarks.

Not a simulator (that is ``hitops.simulate``): each antenna gets a smooth
random-walk phase at the reference band (plus a drift, so the baseline
phases wrap many times); the target band carries R times that phase plus a
constant per-baseline "source" phase; optional complex Gaussian noise.
Because every term is known, the tests can predict exactly what CFPT, PWC
and CWU must return.

A pair is described by a :class:`PairSpec` (the track and bands, with the
phase model, the signal and the storage layout as three small groups) and
written by :func:`make_pair`.  A spec is frozen and hashable, so a test
session can build each distinct pair once and copy it (tests/conftest.py).
The random draws come in a fixed order (walk, reference offsets, source
phases, reference noise, target noise, reference order, target order), so a
spec always gives the same sets, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from ..io.ms_create import ArrayLayout, Band, Field, create_ms

#: station names used by default (the paper's array codes)
DEFAULT_NAMES = ("AP", "SM", "PV", "GL", "PB", "KP", "KC", "KY")


def _as_tuple(value):
    return None if value is None else tuple(value)


@dataclass(frozen=True)
class Troposphere:
    """The reference-band phases: per-antenna random walk and drift, per-baseline constants."""

    #: std of each antenna's per-sample random-walk step at the reference band (keep below
    #: ~1 so the Itoh condition holds)
    step_rad: float = 0.15
    #: per-sample linear drift per antenna, spread evenly over [-drift_rad, +drift_rad]
    drift_rad: float = 0.05
    #: times the antenna number (1..n_ant) added to each antenna phase, so that the baselines
    #: start at different wrap counts (n0 != 0)
    phase_offset_rad: float = 0.0
    #: the reference band's constant per baseline and correlation is uniform in +-pi times
    #: this; it does not close (as source structure would not); 0 makes the reference band
    #: purely antenna-based
    ref_offset_scale: float = 0.3


@dataclass(frozen=True)
class Signal:
    """Amplitudes of both bands and the std of each real/imaginary noise component."""

    ref_amp: float = 1.1
    target_amp: float = 1.0
    sigma_ref: float = 0.0
    sigma_target: float = 0.0


@dataclass(frozen=True)
class Storage:
    """How the rows are stored: order, reversed baselines, time shift, set names."""

    #: store the rows of a band in random order
    shuffle_ref: bool = False
    shuffle_target: bool = False
    #: store the rows of both bands sorted by time (as correlators write them) rather than
    #: baseline by baseline
    time_order: bool = False
    #: baseline indices whose reference rows are stored with the antenna order reversed
    #: (visibility conjugated, RL <-> LR)
    swap_ref_baselines: Tuple[int, ...] = ()
    #: seconds added to the reference TIME column
    ref_time_shift: float = 0.0
    ref_name: str = "ref.ms"
    target_name: str = "target.ms"

    def __post_init__(self):
        object.__setattr__(self, "swap_ref_baselines", tuple(self.swap_ref_baselines))


@dataclass(frozen=True)
class PairSpec:
    """One synthetic pair: track, bands, stations, seed, and the three groups above."""

    n_ant: int = 4
    n_time: int = 300
    dt: float = 1.0
    #: scans are equal slices of the track
    n_scans: int = 1
    t0: float = 5.1e9
    ratio: float = 230.0 / 86.0
    ref_freq_hz: float = 86e9
    corr_types: Tuple[str, ...] = ("RR", "LL")
    #: ANTENNA names; default the first n_ant of DEFAULT_NAMES, the target's the reference's
    ref_names: Optional[Tuple[str, ...]] = None
    target_names: Optional[Tuple[str, ...]] = None
    seed: int = 0
    troposphere: Troposphere = field(default_factory=Troposphere)
    signal: Signal = field(default_factory=Signal)
    storage: Storage = field(default_factory=Storage)

    def __post_init__(self):
        # sequences become tuples, so that a spec is hashable (a cache key)
        for name in ("corr_types", "ref_names", "target_names"):
            object.__setattr__(self, name, _as_tuple(getattr(self, name)))


@dataclass
class PairTruth:
    """What the synthetic pair was built from (per target row, in the target's storage order)."""

    ref_ms: Path
    target_ms: Path
    ratio: float
    ant1: np.ndarray             # target-band ANTENNA1 per target row
    ant2: np.ndarray
    time: np.ndarray
    scan: np.ndarray
    ref_phase_true: np.ndarray   # (n_row, n_corr) unwrapped reference-band phase of the baseline
    source_phase: np.ndarray     # (n_row, n_corr) target-band phase left after perfect FPT
    #: (n_row, n_corr) the reference band's per-baseline constant, which does not close (like
    #: source structure): antenna-based FPT leaves R times it in the output
    ref_offset: np.ndarray
    spec: PairSpec


@dataclass(frozen=True)
class _Rows:
    """Every baseline's whole track, baseline after baseline (the build order)."""

    ant1: np.ndarray
    ant2: np.ndarray
    time: np.ndarray
    scan: np.ndarray
    t_idx: np.ndarray            # index of each row's time in the track
    baseline: np.ndarray         # index of each row's baseline
    n_bl: int


@dataclass(frozen=True)
class _Phases:
    """Per-row (n_row, n_corr) phases of both bands, in build order."""

    ref_true: np.ndarray
    source: np.ndarray
    ref_offset: np.ndarray


def wrap(phase):
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(phase) + np.pi) % (2 * np.pi) - np.pi


def _rows(spec: PairSpec) -> _Rows:
    a1, a2 = np.triu_indices(spec.n_ant, 1)
    times = spec.t0 + spec.dt * np.arange(spec.n_time)
    scan_of_time = 1 + (np.arange(spec.n_time) * spec.n_scans) // spec.n_time
    return _Rows(ant1=np.repeat(a1, spec.n_time), ant2=np.repeat(a2, spec.n_time),
                 time=np.tile(times, a1.size), scan=np.tile(scan_of_time, a1.size),
                 t_idx=np.tile(np.arange(spec.n_time), a1.size),
                 baseline=np.repeat(np.arange(a1.size), spec.n_time), n_bl=a1.size)


def _phases(spec: PairSpec, rows: _Rows, rng) -> _Phases:
    """Drift + random walk per antenna (float64, unwrapped), then the per-baseline constants."""
    tropo, n_ant, n_time = spec.troposphere, spec.n_ant, spec.n_time
    n_corr = len(spec.corr_types)
    drift = tropo.drift_rad * np.linspace(-1.0, 1.0, n_ant)
    walk = np.cumsum(rng.normal(0.0, tropo.step_rad, (n_ant, n_time)), axis=1)
    ant_phase = (walk + drift[:, None] * np.arange(n_time)
                 + tropo.phase_offset_rad * np.arange(1, n_ant + 1)[:, None])
    bl_phase = ant_phase[rows.ant1, rows.t_idx] - ant_phase[rows.ant2, rows.t_idx]
    corr_offset = rng.uniform(-np.pi, np.pi, (rows.n_bl, n_corr)) * tropo.ref_offset_scale
    ref_offset = np.repeat(corr_offset, n_time, axis=0)
    source = np.repeat(rng.uniform(-np.pi, np.pi, (rows.n_bl, n_corr)), n_time, axis=0)
    return _Phases(ref_true=bl_phase[:, None] + ref_offset, source=source, ref_offset=ref_offset)


def _noisy(vis, sigma, rng):
    if not sigma:
        return vis
    return vis + rng.normal(0, sigma, vis.shape) + 1j * rng.normal(0, sigma, vis.shape)


def _swapped_reference(spec: PairSpec, rows: _Rows, ref_vis):
    """ANTENNA1, ANTENNA2 and visibilities of the reference band, some baselines reversed."""
    r_ant1, r_ant2, r_vis = rows.ant1.copy(), rows.ant2.copy(), ref_vis.copy()
    swap = np.isin(rows.baseline, np.asarray(spec.storage.swap_ref_baselines, dtype=np.int64))
    if swap.any():
        reverse = [list(spec.corr_types).index(c[::-1]) for c in spec.corr_types]
        r_ant1[swap], r_ant2[swap] = rows.ant2[swap], rows.ant1[swap]
        r_vis[swap] = np.conj(ref_vis[swap][:, reverse])
    return r_ant1, r_ant2, r_vis


def _write_band(path: Path, spec: PairSpec, names, freq_hz: float, rows: _Rows, order,
                ant1, ant2, vis, time_shift: float = 0.0) -> Path:
    n_ant, n_row = spec.n_ant, rows.time.size
    positions = np.array([[6.0e6 * np.cos(2 * np.pi * k / n_ant),
                           6.0e6 * np.sin(2 * np.pi * k / n_ant), 1.0e5 * k] for k in range(n_ant)])
    main = dict(TIME=rows.time[order] + time_shift, ANTENNA1=ant1[order], ANTENNA2=ant2[order],
                UVW=np.zeros((n_row, 3)), SCAN_NUMBER=rows.scan[order],
                INTERVAL=np.full(n_row, spec.dt), DATA=vis[order].astype(np.complex64))
    return create_ms(path, ArrayLayout(names, names, positions, np.full(n_ant, 12.0)),
                     Band(freq_hz, 2e9, spec.corr_types), Field("SYNTH", 3.276, 0.2163), main,
                     overwrite=True)


def make_pair(directory, spec: PairSpec = PairSpec()) -> PairTruth:
    """Write the reference and target sets of ``spec`` under ``directory``; return the truth."""
    rng = np.random.default_rng(spec.seed)
    directory, storage, sig = Path(directory), spec.storage, spec.signal
    ref_names = list(spec.ref_names or DEFAULT_NAMES[:spec.n_ant])
    target_names = list(spec.target_names or ref_names)
    rows = _rows(spec)
    phases = _phases(spec, rows, rng)
    ref_vis = _noisy(sig.ref_amp * np.exp(1j * phases.ref_true), sig.sigma_ref, rng)
    tgt_vis = _noisy(sig.target_amp * np.exp(1j * (spec.ratio * phases.ref_true + phases.source)),
                     sig.sigma_target, rng)
    n_row = rows.time.size
    stored = np.argsort(rows.time, kind="stable") if storage.time_order else np.arange(n_row)
    ref_order = rng.permutation(n_row) if storage.shuffle_ref else stored
    tgt_order = rng.permutation(n_row) if storage.shuffle_target else stored
    r_ant1, r_ant2, r_vis = _swapped_reference(spec, rows, ref_vis)
    ref_ms = _write_band(directory / storage.ref_name, spec, ref_names, spec.ref_freq_hz, rows,
                         ref_order, r_ant1, r_ant2, r_vis, storage.ref_time_shift)
    target_ms = _write_band(directory / storage.target_name, spec, target_names,
                            spec.ref_freq_hz * spec.ratio, rows, tgt_order, rows.ant1, rows.ant2,
                            tgt_vis)
    o = tgt_order
    return PairTruth(ref_ms=ref_ms, target_ms=target_ms, ratio=spec.ratio, ant1=rows.ant1[o],
                     ant2=rows.ant2[o], time=rows.time[o], scan=rows.scan[o],
                     ref_phase_true=phases.ref_true[o], source_phase=phases.source[o],
                     ref_offset=phases.ref_offset[o], spec=spec)


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
