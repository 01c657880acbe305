"""Scene files: parse, fill defaults from the station catalogue, validate.

A scene is YAML with sections ``source``, ``observation``, ``bands``,
``corruptions`` and ``stations`` (docs/simulate.md has the full reference).
A station may be given by its code alone (looked up in
``hitops/scenes/stations.yml``) or as a mapping that overrides catalogue
fields or defines a new station completely.  Every error names the file and
the field (``stations[2].bands.230.t_rx``) and says what to do.
"""

from __future__ import annotations

import copy
import importlib.resources
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import yaml

from ..errors import SceneError
from .scene_parts import (BandSpec, Calibrator, Instrumental, SourceComponent, parse_band,
                          parse_calibrator, parse_component, parse_instrumental)

PACKAGED_SCENES = ("paper", "demo", "triband", "ngeht", "wideband", "phaseref")
#: default phase coherence length at 230 GHz (m) turning a wind speed into t_c = r0 / v
#: (10 m/s gives 10 s, the typical EHT value at 230 GHz; see docs/simulate.md)
DEFAULT_R0_230 = 100.0
WEATHER_KEYS = ("source", "site", "date", "year", "month", "statistic", "fallback", "r0")
VALID_CORRELATIONS = ("RR", "RL", "LR", "LL", "XX", "XY", "YX", "YY")

#: approximate zenith opacity from precipitable water vapour, tau = dry + wet * PWV.
#: 230 GHz: the JCMT/CSO tipper relation tau_225 = 0.04 PWV + 0.017 (Dempsey et
#: al. 2013, MNRAS 430, 2534).  86 GHz: ASSUMED (oxygen-dominated dry term plus
#: a small water term); give ``tau`` directly for anything quantitative.
PWV_TO_TAU = {230e9: (0.017, 0.04), 86e9: (0.03, 0.006)}

STATION_DEFAULTS = {"elevation_limit": 10.0}
BAND_DEFAULTS = {"aperture_efficiency": 0.5, "t_atm": 270.0}


@dataclass(frozen=True)
class StationBand:
    antenna_name: str        # ANTENNA::NAME in this band's MS (paired antennas may differ)
    t_rx: float              # receiver temperature, K
    aperture_efficiency: float
    tau: float               # zenith opacity
    t_atm: float             # physical temperature of the absorbing atmosphere, K
    instrumental: Optional[Instrumental] = None   # phase and delay of the signal chain


@dataclass(frozen=True)
class WeatherSpec:
    """Where a station's weather comes from (``weather:`` in the scene or the station)."""

    source: str              # 'merra2'
    site: str                # site name or station code asked for (a proxy is resolved later)
    date: Optional[str]      # ISO date the observation's first day is mapped onto
    year: Optional[int]      # substitute year for the date
    month: Optional[int]     # with statistic, when no date is given
    statistic: str           # mean, median, good, bad
    fallback: str            # 'climatology' or 'error' for a date not in the tables
    r0: float                # m, phase coherence length at 230 GHz: t_c(230 GHz) = r0 / wind
    bands: tuple             # band names whose opacity and sky temperature come from the tables
    coherence: bool          # True: the coherence time comes from the wind


@dataclass(frozen=True)
class Station:
    code: str
    name: str
    itrf: np.ndarray         # (3,) metres
    diameter: float          # metres
    elevation_limit: float   # degrees
    coherence_time: float    # zenith t_c (s) at the scene's coherence frequency
    bands: Dict[str, StationBand]
    weather: Optional[WeatherSpec] = None


@dataclass(frozen=True)
class Scene:
    name: str
    source_name: str
    ra: float                # rad, J2000
    dec: float               # rad, J2000
    flux: Dict[str, float]   # point-source flux density per band, Jy
    components: List[SourceComponent]
    start_mjd_s: float       # UTC, MJD seconds
    duration: float          # s
    integration: float       # s
    scan_length: Optional[float]
    scan_gap: float
    correlations: List[str]
    bands: List[BandSpec]    # reference band first
    troposphere: bool
    noise: bool
    seed: int
    coherence_freq_hz: float
    coherence_scale: float
    quantisation_efficiency: float
    telescope: str
    stations: List[Station] = field(default_factory=list)
    source_file: str = ""
    #: noise and turbulence use max(elevation, this) (deg); None: 1 deg for the noise and
    #: the station's elevation limit for the turbulence
    airmass_elevation_floor: Optional[float] = None
    #: a phase calibrator in scans alternating with the target's (None: the target only)
    calibrator: Optional[Calibrator] = None


def _catalogue() -> Dict[str, Any]:
    text = importlib.resources.files("hitops.scenes").joinpath("stations.yml").read_text()
    return yaml.safe_load(text)


def load_scene_mapping(scene: str | Path | dict) -> tuple[dict, str]:
    """The raw mapping of a scene given as a mapping, a YAML path or a packaged name."""
    if isinstance(scene, dict):
        return copy.deepcopy(scene), "<dict>"
    text_name = str(scene)
    if text_name in PACKAGED_SCENES:
        res = importlib.resources.files("hitops.scenes").joinpath(f"{text_name}.yml")
        return yaml.safe_load(res.read_text()), f"packaged scene '{text_name}'"
    path = Path(text_name)
    if not path.is_file():
        raise SceneError(f"scene '{text_name}' is neither a file nor a packaged scene "
                         f"({', '.join(PACKAGED_SCENES)}); give a YAML path or one of those names")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise SceneError(f"scene {path}: not valid YAML: {err}") from err
    if not isinstance(data, dict):
        raise SceneError(f"scene {path}: expected a mapping with source, observation, bands, "
                         "corruptions and stations")
    return data, str(path)


class _Reader:
    """Field access that names the file and the field in every error."""

    def __init__(self, origin: str):
        self.origin = origin

    def fail(self, where: str, what: str):
        raise SceneError(f"scene {self.origin}: field '{where}' {what}")

    def section(self, data: dict, key: str, where: str = "") -> dict:
        full = f"{where}.{key}" if where else key
        if key not in data or data[key] is None:
            self.fail(full, "is missing")
        if not isinstance(data[key], dict):
            self.fail(full, "must be a mapping")
        return data[key]

    def number(self, data: dict, key: str, where: str, default=None, minimum=None,
               strictly_positive=False, required=True) -> Optional[float]:
        full = f"{where}.{key}" if where else key
        value = data.get(key, default)
        if value is None:
            if required:
                self.fail(full, "is missing")
            return None
        try:
            value = float(value)
        except (TypeError, ValueError):
            self.fail(full, f"must be a number, got {value!r}")
        if not np.isfinite(value):
            self.fail(full, f"must be finite, got {value}")
        if strictly_positive and value <= 0:
            self.fail(full, f"must be > 0, got {value:g}")
        if minimum is not None and value < minimum:
            self.fail(full, f"must be >= {minimum:g}, got {value:g}")
        return value

    def check_keys(self, data: dict, allowed, where: str):
        unknown = sorted(set(map(str, data)) - set(allowed))
        if unknown:
            self.fail(f"{where}.{unknown[0]}" if where else unknown[0],
                      f"is not a known field (known: {', '.join(sorted(allowed))})")


def _angle(reader: _Reader, value, where: str, kind: str) -> float:
    """An angle in radians from 'hms'/'dms' text or a number in degrees."""
    if isinstance(value, (int, float)):
        return float(np.radians(value))
    from casacore import quanta as qa

    try:
        q = qa.quantity(str(value))
        return float(q.get_value("rad"))
    except Exception:  # casacore raises RuntimeError with its own text
        reader.fail(where, f"is not a {kind} ('12h30m49.42s' / '+12d23m28.04s' or degrees): "
                           f"{value!r}")


def _time_mjd_s(reader: _Reader, value, where: str) -> float:
    from casacore import quanta as qa

    text = value.isoformat() if hasattr(value, "isoformat") else str(value)
    try:
        q = qa.quantity(text.replace(" ", "T"))
        return float(q.get_value("s"))
    except Exception:
        reader.fail(where, f"is not a UTC time like '2023-04-10T00:00:00': {value!r}")


def _per_band(reader: _Reader, data, where: str, band_names, minimum=0.0) -> Dict[str, float]:
    if not isinstance(data, dict):
        reader.fail(where, "must map band name to value, e.g. {'86': 1.1, '230': 1.0}")
    data = {str(k): v for k, v in data.items()}
    out = {}
    for name in band_names:
        out[name] = reader.number(data, name, where, minimum=minimum)
    return out


def _weather_options(reader: _Reader, data, where: str) -> Optional[dict]:
    """A validated weather mapping (None: no weather); 'none'/false switch it off."""
    if data is None or data is False or (isinstance(data, str) and data.lower() in ("none", "off")):
        return None
    if not isinstance(data, dict):
        reader.fail(where, "must be a mapping like {source: merra2, date: 2023-04-10} or none")
    data = {str(k): v for k, v in data.items()}
    reader.check_keys(data, WEATHER_KEYS, where)
    from ..weather.tables import STATISTICS, parse_date, WeatherError

    source = str(data.get("source", "merra2")).lower()
    if source in ("none", "off"):
        return None
    if source != "merra2":
        reader.fail(f"{where}.source", f"must be merra2 (or none), got {source!r}")
    out = {"source": source, "site": data.get("site"), "date": None, "year": None,
           "month": None, "statistic": str(data.get("statistic", "median")),
           "fallback": str(data.get("fallback", "climatology")),
           "r0": reader.number(data, "r0", where, default=DEFAULT_R0_230, strictly_positive=True)}
    if data.get("date") is not None:
        try:
            out["date"] = parse_date(data["date"]).isoformat()
        except WeatherError:
            reader.fail(f"{where}.date", f"is not a date like 2023-04-10: {data['date']!r}")
    if data.get("year") is not None:
        year = data["year"]
        if not isinstance(year, int) or not 1900 < year < 2200:
            reader.fail(f"{where}.year", f"must be a year like 2018, got {year!r}")
        out["year"] = year
    if data.get("month") is not None:
        month = data["month"]
        if not isinstance(month, int) or not 1 <= month <= 12:
            reader.fail(f"{where}.month", f"must be a month number 1-12, got {month!r}")
        out["month"] = month
    if out["statistic"] not in STATISTICS:
        reader.fail(f"{where}.statistic", f"must be one of {', '.join(STATISTICS)}, "
                    f"got {out['statistic']!r}")
    if out["fallback"] not in ("climatology", "error"):
        reader.fail(f"{where}.fallback", f"must be climatology or error, got {out['fallback']!r}")
    return out


def _weather_spec(reader: _Reader, options: Optional[dict], entry: dict, code: str,
                  bands: List[BandSpec], where: str) -> Optional[WeatherSpec]:
    """The station's WeatherSpec: bands and coherence not given explicitly in the scene."""
    if options is None:
        return None
    from ..weather.tables import WeatherError, band_column, resolve_site

    explicit = {str(k): (v or {}) for k, v in (entry.get("bands") or {}).items()}
    from_tables = tuple(b.name for b in bands
                        if not ({"tau", "pwv"} & set(explicit.get(b.name, {}))))
    coherence = not ({"coherence_time", "wind_speed"} & set(entry))
    if not from_tables and not coherence:
        return None
    try:
        folder, _ = resolve_site(options["site"] or code, code)
        for b in bands:
            if b.name in from_tables:
                band_column(b.freq_hz, b.name, code, folder)
    except WeatherError as err:
        reader.fail(f"{where}.weather", f"cannot be met: {err}")
    # no date and no month: the observation's own date (resolved when the time grid is known)
    return WeatherSpec(options["source"], options["site"] or code, options["date"], options["year"],
                       options["month"],
                       options["statistic"], options["fallback"], options["r0"], from_tables,
                       coherence)


def _station(reader: _Reader, entry, index: int, catalogue: dict, bands: List[BandSpec],
             scene_weather: Optional[dict] = None) -> Station:
    where = f"stations[{index}]"
    if isinstance(entry, str):
        entry = {"code": entry}
    if not isinstance(entry, dict) or "code" not in entry:
        reader.fail(where, "must be a station code or a mapping with 'code'")
    code = str(entry["code"])
    base = copy.deepcopy(catalogue.get(code, {}))
    if not base and "itrf" not in entry:
        reader.fail(f"{where}.code", f"names unknown station '{code}': it is not in the "
                    f"station catalogue ({', '.join(sorted(catalogue))}); give its itrf, "
                    "diameter, coherence_time and bands in the scene")
    reader.check_keys(entry, ("code", "name", "itrf", "diameter", "elevation_limit",
                              "coherence_time", "wind_speed", "r0", "bands", "weather"), where)
    options = scene_weather
    if "weather" in entry:
        own = entry["weather"]
        if isinstance(own, dict) and scene_weather is not None:
            own = {**{k: v for k, v in scene_weather.items() if v is not None}, **own}
        options = _weather_options(reader, own, f"{where}.weather")
    merged = {**STATION_DEFAULTS, **base,
              **{k: v for k, v in entry.items() if k not in ("bands", "weather")}}
    merged_bands = {str(k): dict(v or {}) for k, v in (base.get("bands") or {}).items()}
    for k, v in (entry.get("bands") or {}).items():
        merged_bands.setdefault(str(k), {}).update(v or {})

    itrf = merged.get("itrf")
    if not isinstance(itrf, (list, tuple)) or len(itrf) != 3:
        reader.fail(f"{where}.itrf", "must be [X, Y, Z] in metres (ITRF)")
    itrf = np.array([reader.number({"v": x}, "v", f"{where}.itrf") for x in itrf])
    if np.linalg.norm(itrf) < 6.3e6 or np.linalg.norm(itrf) > 6.4e6:
        reader.fail(f"{where}.itrf", f"is {np.linalg.norm(itrf) / 1e3:.0f} km from the geocentre; "
                    "give ITRF X, Y, Z in metres")
    diameter = reader.number(merged, "diameter", where, strictly_positive=True)
    # negative limits (down to -90: every row) only serve row-throughput benchmarks
    elevation_limit = reader.number(merged, "elevation_limit", where, minimum=-90.0)
    if elevation_limit >= 90:
        reader.fail(f"{where}.elevation_limit", f"must be below 90 degrees, got {elevation_limit}")
    if merged.get("coherence_time") is not None and "wind_speed" not in entry:
        coherence = reader.number(merged, "coherence_time", where, strictly_positive=True)
    elif merged.get("wind_speed") is not None:
        # frozen flow: D(dt) = (v dt / r0)^(5/3), so t_c = r0 / v
        wind = reader.number(merged, "wind_speed", where, strictly_positive=True)
        r0 = reader.number(merged, "r0", where, strictly_positive=True)
        coherence = r0 / wind
    else:
        reader.fail(f"{where}.coherence_time", "is missing (or give wind_speed and r0)")

    station_bands = {}
    for band in bands:
        bwhere = f"{where}.bands.{band.name}"
        raw = merged_bands.get(band.name)
        if raw is None:
            reader.fail(bwhere, f"is missing: station {code} has no values for band {band.name}")
        reader.check_keys(raw, ("name", "t_rx", "aperture_efficiency", "tau", "pwv", "t_atm",
                                "instrumental"), bwhere)
        raw = {**BAND_DEFAULTS, **raw}
        t_rx = reader.number(raw, "t_rx", bwhere, minimum=0.0)
        eff = reader.number(raw, "aperture_efficiency", bwhere, strictly_positive=True)
        if eff > 1:
            reader.fail(f"{bwhere}.aperture_efficiency", f"must be <= 1, got {eff}")
        t_atm = reader.number(raw, "t_atm", bwhere, minimum=0.0)
        if raw.get("tau") is not None:
            tau = reader.number(raw, "tau", bwhere, minimum=0.0)
        elif raw.get("pwv") is not None:
            pwv = reader.number(raw, "pwv", bwhere, minimum=0.0)
            nearest = min(PWV_TO_TAU, key=lambda f: abs(f - band.freq_hz))
            dry, wet = PWV_TO_TAU[nearest]
            tau = dry + wet * pwv
        elif options is not None:
            tau = float("nan")        # from the weather tables (checked by _weather_spec)
        else:
            reader.fail(f"{bwhere}.tau", "is missing (give tau, the zenith opacity, or pwv in mm, "
                        "or weather: {source: merra2})")
        station_bands[band.name] = StationBand(
            str(raw.get("name", code)), t_rx, eff, tau, t_atm,
            parse_instrumental(reader, raw.get("instrumental"), f"{bwhere}.instrumental"))
    weather = _weather_spec(reader, options, entry, code, bands, where)
    return Station(code, str(merged.get("name", code)), itrf, diameter, elevation_limit,
                   coherence, station_bands, weather)


def parse_scene(scene: str | Path | dict) -> Scene:
    """A validated :class:`Scene` from a YAML path, a packaged scene name or a mapping."""
    data, origin = load_scene_mapping(scene)
    reader = _Reader(origin)
    reader.check_keys(data, ("name", "source", "observation", "bands", "corruptions", "stations",
                             "weather", "calibrator"), "")

    raw_bands = data.get("bands")
    if not isinstance(raw_bands, list) or not raw_bands:
        reader.fail("bands", "is missing: give a list of {name, freq_ghz, bandwidth_ghz}, "
                             "reference band first")
    bands = [parse_band(reader, b, f"bands[{i}]") for i, b in enumerate(raw_bands)]
    names = [b.name for b in bands]
    if len(set(names)) != len(names):
        reader.fail("bands", f"has repeated band names {names}")

    source = reader.section(data, "source")
    reader.check_keys(source, ("name", "ra", "dec", "flux", "components"), "source")
    for key in ("ra", "dec", "flux"):
        if source.get(key) is None:
            reader.fail(f"source.{key}", "is missing")
    ra = _angle(reader, source["ra"], "source.ra", "right ascension")
    dec = _angle(reader, source["dec"], "source.dec", "declination")
    if abs(dec) > np.pi / 2:
        reader.fail("source.dec", "must lie within +-90 degrees")
    flux = _per_band(reader, source["flux"], "source.flux", names)
    components = [parse_component(reader, c, f"source.components[{i}]", names, _per_band)
                  for i, c in enumerate(source.get("components") or [])]

    obs = reader.section(data, "observation")
    reader.check_keys(obs, ("start", "duration", "integration", "scan_length", "scan_gap",
                            "correlations", "telescope"), "observation")
    if obs.get("start") is None:
        reader.fail("observation.start", "is missing")
    start = _time_mjd_s(reader, obs["start"], "observation.start")
    duration = reader.number(obs, "duration", "observation", strictly_positive=True)
    integration = reader.number(obs, "integration", "observation", strictly_positive=True)
    if integration > duration:
        reader.fail("observation.integration", f"({integration:g} s) is longer than "
                    f"observation.duration ({duration:g} s)")
    scan_length = reader.number(obs, "scan_length", "observation", required=False,
                                strictly_positive=True)
    scan_gap = reader.number(obs, "scan_gap", "observation", default=0.0, minimum=0.0)
    if scan_length is not None and scan_length < integration:
        reader.fail("observation.scan_length", f"({scan_length:g} s) is shorter than one "
                    f"integration ({integration:g} s)")
    correlations = obs.get("correlations", ["RR", "LL"])
    if isinstance(correlations, str):
        correlations = [c.strip() for c in correlations.split(",") if c.strip()]
    bad = [c for c in correlations if c not in VALID_CORRELATIONS]
    if bad or not correlations:
        reader.fail("observation.correlations", f"must be a list from {VALID_CORRELATIONS}, "
                    f"got {correlations}")
    kinds = {c[0] in "RL" for c in correlations}
    if len(kinds) > 1:
        reader.fail("observation.correlations", "mixes circular and linear products")

    corr = data.get("corruptions") or {}
    if not isinstance(corr, dict):
        reader.fail("corruptions", "must be a mapping")
    reader.check_keys(corr, ("troposphere", "noise", "seed", "coherence_freq_ghz",
                             "coherence_scale", "quantisation_efficiency",
                             "airmass_elevation_floor"), "corruptions")
    airmass_floor = reader.number(corr, "airmass_elevation_floor", "corruptions",
                                  required=False, minimum=0.0)
    if airmass_floor is not None and airmass_floor >= 90:
        reader.fail("corruptions.airmass_elevation_floor", f"must be below 90, got {airmass_floor}")
    coherence_freq = reader.number(corr, "coherence_freq_ghz", "corruptions", default=230.0,
                                   strictly_positive=True) * 1e9
    coherence_scale = reader.number(corr, "coherence_scale", "corruptions", default=1.0,
                                    strictly_positive=True)
    eta_q = reader.number(corr, "quantisation_efficiency", "corruptions", default=0.88,
                          strictly_positive=True)
    seed = corr.get("seed", 0)
    if not isinstance(seed, int) or seed < 0:
        reader.fail("corruptions.seed", f"must be a non-negative integer, got {seed!r}")

    raw_stations = data.get("stations")
    if not isinstance(raw_stations, list) or len(raw_stations) < 2:
        reader.fail("stations", "is missing or lists fewer than two stations")
    catalogue = _catalogue()
    scene_weather = _weather_options(reader, data.get("weather"), "weather")
    stations = [_station(reader, entry, i, catalogue, bands, scene_weather)
                for i, entry in enumerate(raw_stations)]
    codes = [s.code for s in stations]
    if len(set(codes)) != len(codes):
        reader.fail("stations", f"lists a station twice: {codes}")

    calibrator = None
    if data.get("calibrator") is not None:
        calibrator = parse_calibrator(reader, data["calibrator"], str(source.get("name", "SOURCE")),
                                      _angle, _per_band, names)
        _require_target_scans(reader, scan_length, calibrator)
    return Scene(name=str(data.get("name", Path(origin).stem)),
                 source_name=str(source.get("name", "SOURCE")), ra=ra, dec=dec, flux=flux,
                 components=components, start_mjd_s=start, duration=duration,
                 integration=integration, scan_length=scan_length, scan_gap=scan_gap,
                 correlations=list(correlations), bands=bands,
                 troposphere=bool(corr.get("troposphere", True)),
                 noise=bool(corr.get("noise", True)), seed=int(seed),
                 coherence_freq_hz=coherence_freq, coherence_scale=coherence_scale,
                 quantisation_efficiency=eta_q, telescope=str(obs.get("telescope", "VLBA")),
                 stations=stations, source_file=origin, airmass_elevation_floor=airmass_floor,
                 calibrator=calibrator)


def _require_target_scans(reader: _Reader, scan_length: Optional[float],
                          calibrator: Optional[Calibrator]) -> None:
    """A calibrator needs target scans to alternate with: observation.scan_length."""
    if calibrator is not None and scan_length is None:
        reader.fail("observation.scan_length", "is missing: with a calibrator the target is "
                    "observed in scans of this length (s), alternating with calibrator scans of "
                    "calibrator.scan_length, observation.scan_gap apart")


def apply_overrides(scene: Scene, *, duration=None, integration=None, seed=None,
                    coherence_scale=None, no_noise=False, no_troposphere=False,
                    stations=None, start=None, scan_length=None, scan_gap=None,
                    correlations=None) -> Scene:
    """A copy of ``scene`` with command-line overrides applied and re-validated."""
    reader = _Reader(f"{scene.source_file} (command-line override)")
    changes: Dict[str, Any] = {}
    if duration is not None:
        changes["duration"] = reader.number({"duration": duration}, "duration", "observation",
                                            strictly_positive=True)
    if integration is not None:
        changes["integration"] = reader.number({"integration": integration}, "integration",
                                               "observation", strictly_positive=True)
    if start is not None:
        changes["start_mjd_s"] = _time_mjd_s(reader, start, "observation.start")
    if scan_length is not None:
        changes["scan_length"] = (None if float(scan_length) == 0 else reader.number(
            {"scan_length": scan_length}, "scan_length", "observation", strictly_positive=True))
    if scan_gap is not None:
        changes["scan_gap"] = reader.number({"scan_gap": scan_gap}, "scan_gap", "observation",
                                            minimum=0.0)
    if seed is not None:
        if int(seed) < 0:
            reader.fail("corruptions.seed", f"must be a non-negative integer, got {seed}")
        changes["seed"] = int(seed)
    if coherence_scale is not None:
        changes["coherence_scale"] = reader.number({"coherence_scale": coherence_scale},
                                                   "coherence_scale", "corruptions",
                                                   strictly_positive=True)
    if no_noise:
        changes["noise"] = False
    if no_troposphere:
        changes["troposphere"] = False
    if correlations:
        corrs = [c.strip() for c in str(correlations).split(",") if c.strip()]
        bad = [c for c in corrs if c not in VALID_CORRELATIONS]
        if bad or not corrs or len({c[0] in "RL" for c in corrs}) > 1:
            reader.fail("observation.correlations", f"must be circular or linear products from "
                        f"{VALID_CORRELATIONS}, got {corrs}")
        changes["correlations"] = corrs
    if stations:
        wanted = [s.strip() for s in str(stations).split(",") if s.strip()]
        known = {s.code: s for s in scene.stations}
        unknown = [w for w in wanted if w not in known]
        if unknown:
            reader.fail("stations", f"names unknown station(s) {unknown}; the scene has "
                        f"{', '.join(known)}")
        if len(set(wanted)) < 2:
            reader.fail("stations", "must keep at least two stations")
        changes["stations"] = [known[w] for w in wanted]
    new = replace(scene, **changes)
    if new.integration > new.duration:
        reader.fail("observation.integration", f"({new.integration:g} s) is longer than "
                    f"observation.duration ({new.duration:g} s)")
    _require_target_scans(reader, new.scan_length, new.calibrator)
    if new.scan_length is not None and new.scan_length < new.integration:
        reader.fail("observation.scan_length", f"({new.scan_length:g} s) is shorter than one "
                    f"integration ({new.integration:g} s)")
    return new
