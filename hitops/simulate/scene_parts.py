"""The wideband parts of a scene: bands with windows and channels, source components,
per-station instrumental phase and delay.

Each parser takes the scene's field reader (``scene._Reader``: ``number``,
``check_keys``, ``fail``), so every error names the file and the field.

Channel layout of a band (docs/simulate.md, "Wideband"): ``windows_ghz`` lists
the centre of each spectral window (default: the band's ``freq_ghz``), every
window holds ``n_chan`` channels of width ``bandwidth_ghz / n_chan`` (or
``chan_width_mhz``), and channel k of a window sits at

    nu_k = centre + (k - (n_chan - 1) / 2) * chan_width,

so a one-channel window's only channel is its centre (the single-channel scenes
keep their frequencies exactly).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

#: source component shapes (docs/simulate.md, "Source models")
SHAPES = ("gaussian", "ring")
COMPONENT_KEYS = ("shape", "flux", "offset_ra", "offset_dec", "fwhm_major", "fwhm_minor",
                  "position_angle", "diameter", "width")
INSTRUMENTAL_KEYS = ("phase_deg", "delay_ns", "phase_drift_deg_per_hour",
                     "delay_drift_ns_per_hour")
BAND_KEYS = ("name", "freq_ghz", "bandwidth_ghz", "n_chan", "chan_width_mhz", "windows_ghz")
CALIBRATOR_KEYS = ("name", "ra", "dec", "flux", "scan_length")
#: optional keys of the calibrator mapping
CALIBRATOR_OPTIONAL = ("own_troposphere", "components")


@dataclass(frozen=True)
class BandSpec:
    """One observing band: its nominal frequency and its spectral windows."""

    name: str
    freq_hz: float                         # nominal frequency: weather, flux and delay reference
    bandwidth_hz: float                    # width of each window
    windows_hz: Tuple[float, ...] = ()     # window centres, increasing (empty: (freq_hz,))
    n_chan: int = 1                        # channels per window
    chan_width_hz: float = 0.0             # 0: bandwidth_hz / n_chan

    @property
    def centres_hz(self) -> Tuple[float, ...]:
        return self.windows_hz or (self.freq_hz,)

    @property
    def n_window(self) -> int:
        return len(self.centres_hz)

    @property
    def channel_width_hz(self) -> float:
        return self.chan_width_hz or self.bandwidth_hz / self.n_chan

    @property
    def is_wideband(self) -> bool:
        """More than one channel or window: written with hitops.simulate.ms_windows."""
        return self.n_chan > 1 or self.n_window > 1

    def chan_freq(self) -> np.ndarray:
        """Channel frequencies (Hz), (n_window, n_chan), increasing within each window."""
        offsets = (np.arange(self.n_chan) - (self.n_chan - 1) / 2.0) * self.channel_width_hz
        return np.asarray(self.centres_hz, dtype=np.float64)[:, None] + offsets[None, :]


@dataclass(frozen=True)
class Instrumental:
    """Instrumental phase of one station in one band (the paper's phi_inst / Phi_inst).

    phase(t, nu) = phase + phase_rate (t - t0) + 2 pi (nu - nu_band) (delay + delay_rate (t - t0)),
    t0 the observation's start, nu_band the band's nominal frequency.
    """

    phase: float = 0.0          # rad
    delay: float = 0.0          # s
    phase_rate: float = 0.0     # rad/s
    delay_rate: float = 0.0     # s/s

    def series(self, elapsed: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(phase at the nominal frequency (rad), delay (s)) on the time grid."""
        return self.phase + self.phase_rate * elapsed, self.delay + self.delay_rate * elapsed


@dataclass(frozen=True)
class Calibrator:
    """A phase calibrator observed in scans alternating with the target's (docs/simulate.md,
    "Calibrator field"): a point source at its own phase centre (FIELD_ID 1), plus any
    ``components`` (then resolved: its model is written to MODEL_DATA)."""

    name: str
    ra: float                # rad, J2000
    dec: float               # rad, J2000
    flux: Dict[str, float]   # Jy per band
    scan_length: float       # s, each calibrator scan
    # each field's own part of the path, as a fraction of the shared part's rms (0: both
    # fields see one troposphere, as before)
    own_troposphere: float = 0.0
    # components beside the point (the source's component syntax, offsets and sizes in uas)
    components: Tuple["SourceComponent", ...] = ()


@dataclass(frozen=True)
class SourceComponent:
    """A component beside the point source (offsets east/north, sizes in uas)."""

    flux: Dict[str, float]   # Jy per band
    offset_ra: float         # uas, towards east (l)
    offset_dec: float        # uas, towards north (m)
    fwhm_major: float        # uas (gaussian: its FWHM; ring: the blur's FWHM)
    fwhm_minor: float        # uas
    position_angle: float    # degrees east of north
    shape: str = "gaussian"
    diameter: float = 0.0    # uas, ring only


def parse_band(reader, raw, where: str) -> BandSpec:
    """A BandSpec from ``{name, freq_ghz, bandwidth_ghz}`` plus optional
    ``n_chan``, ``chan_width_mhz`` and ``windows_ghz``."""
    if not isinstance(raw, dict) or "name" not in raw:
        reader.fail(f"{where}.name", "is missing")
    reader.check_keys(raw, BAND_KEYS, where)
    freq = reader.number(raw, "freq_ghz", where, strictly_positive=True) * 1e9
    bandwidth = reader.number(raw, "bandwidth_ghz", where, strictly_positive=True) * 1e9
    n_chan = raw.get("n_chan", 1)
    if isinstance(n_chan, bool) or not isinstance(n_chan, int) or n_chan < 1:
        reader.fail(f"{where}.n_chan", f"must be a whole number >= 1, got {n_chan!r}")
    width = 0.0
    if raw.get("chan_width_mhz") is not None:
        width = reader.number(raw, "chan_width_mhz", where, strictly_positive=True) * 1e6
        if width * n_chan > bandwidth * (1 + 1e-9):
            reader.fail(f"{where}.chan_width_mhz", f"({width / 1e6:g} MHz) x n_chan ({n_chan}) "
                        f"exceeds the window width bandwidth_ghz ({bandwidth / 1e9:g} GHz)")
    centres: Tuple[float, ...] = ()
    if raw.get("windows_ghz") is not None:
        listed = raw["windows_ghz"]
        if not isinstance(listed, (list, tuple)) or not listed:
            reader.fail(f"{where}.windows_ghz", "must be a list of window centres in GHz")
        centres = tuple(reader.number({"v": v}, "v", f"{where}.windows_ghz",
                                      strictly_positive=True) * 1e9 for v in listed)
        gaps = np.diff(centres)
        if np.any(gaps < bandwidth * (1 - 1e-9)):
            reader.fail(f"{where}.windows_ghz", f"{[c / 1e9 for c in centres]} must increase by "
                        f"at least the window width ({bandwidth / 1e9:g} GHz): windows may "
                        "not overlap and are listed lowest first")
    return BandSpec(str(raw["name"]), freq, bandwidth, centres, n_chan, width)


def parse_instrumental(reader, raw, where: str) -> Optional[Instrumental]:
    """Instrumental terms of a station band (None when not given or all zero)."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        reader.fail(where, "must be a mapping like {phase_deg: 30, delay_ns: 0.2}")
    reader.check_keys(raw, INSTRUMENTAL_KEYS, where)
    values = {key: reader.number(raw, key, where, default=0.0) for key in INSTRUMENTAL_KEYS}
    terms = Instrumental(phase=np.radians(values["phase_deg"]), delay=values["delay_ns"] * 1e-9,
                         phase_rate=np.radians(values["phase_drift_deg_per_hour"]) / 3600.0,
                         delay_rate=values["delay_drift_ns_per_hour"] * 1e-9 / 3600.0)
    return terms if any(v != 0.0 for v in values.values()) else None


def parse_component(reader, raw, where: str, band_names, per_band) -> SourceComponent:
    """A source component; ``per_band`` reads a {band: value} mapping (scene._per_band)."""
    if not isinstance(raw, dict):
        reader.fail(where, "must be a mapping")
    reader.check_keys(raw, COMPONENT_KEYS, where)
    if raw.get("flux") is None:
        reader.fail(f"{where}.flux", "is missing")
    shape = str(raw.get("shape", "gaussian")).lower()
    if shape not in SHAPES:
        reader.fail(f"{where}.shape", f"must be one of {', '.join(SHAPES)}, got {shape!r}")
    diameter = reader.number(raw, "diameter", where, default=0.0, minimum=0.0)
    if shape == "ring" and not diameter > 0:
        reader.fail(f"{where}.diameter", "must be > 0 (uas) for a ring")
    if shape != "ring" and raw.get("diameter") is not None:
        reader.fail(f"{where}.diameter", "applies to shape: ring only")
    if shape == "ring":
        # a ring's blur is circular: 'width' (uas FWHM) or fwhm_major
        major = reader.number(raw, "width", where, default=raw.get("fwhm_major", 0.0),
                              minimum=0.0)
        minor = major
    else:
        if raw.get("width") is not None:
            reader.fail(f"{where}.width", "applies to shape: ring only (give fwhm_major)")
        major = reader.number(raw, "fwhm_major", where, minimum=0.0)
        minor = reader.number(raw, "fwhm_minor", where, default=major, minimum=0.0)
    return SourceComponent(per_band(reader, raw["flux"], f"{where}.flux", band_names),
                           reader.number(raw, "offset_ra", where, default=0.0),
                           reader.number(raw, "offset_dec", where, default=0.0),
                           major, minor, reader.number(raw, "position_angle", where, default=0.0),
                           shape, diameter)


def parse_calibrator(reader, raw, target_name: str, angle, per_band, band_names) -> Calibrator:
    """The scene's ``calibrator`` mapping; ``angle`` and ``per_band`` are scene.py's readers
    (right ascension / declination text, {band: value} mappings)."""
    if not isinstance(raw, dict):
        reader.fail("calibrator", "must be a mapping {name, ra, dec, flux, scan_length}")
    reader.check_keys(raw, CALIBRATOR_KEYS + CALIBRATOR_OPTIONAL, "calibrator")
    for key in CALIBRATOR_KEYS:
        if raw.get(key) is None:
            reader.fail(f"calibrator.{key}", "is missing")
    name = str(raw["name"])
    if name == target_name:
        reader.fail("calibrator.name", f"'{name}' is the target's name (source.name); the two "
                    "fields are told apart by FIELD::NAME, give the calibrator its own")
    dec = angle(reader, raw["dec"], "calibrator.dec", "declination")
    if abs(dec) > np.pi / 2:
        reader.fail("calibrator.dec", "must lie within +-90 degrees")
    return Calibrator(name, angle(reader, raw["ra"], "calibrator.ra", "right ascension"), dec,
                      per_band(reader, raw["flux"], "calibrator.flux", band_names, 0.0),
                      reader.number(raw, "scan_length", "calibrator", strictly_positive=True),
                      reader.number(raw, "own_troposphere", "calibrator", default=0.0,
                                    minimum=0.0),
                      _calibrator_components(reader, raw.get("components"), per_band,
                                             band_names))


def _calibrator_components(reader, raw, per_band, band_names) -> Tuple[SourceComponent, ...]:
    """``calibrator.components``: a list in the source's component syntax (or absent)."""
    if raw is None:
        return ()
    if not isinstance(raw, (list, tuple)):
        reader.fail("calibrator.components", "must be a list of components like "
                    "{flux: {\"86\": 0.5, \"230\": 0.3}, offset_ra: 100, fwhm_major: 50}")
    return tuple(parse_component(reader, c, f"calibrator.components[{i}]", band_names, per_band)
                 for i, c in enumerate(raw))
