"""The shipped MERRA-2 extract: loading, and weather per station on a time grid.

Two tables (built by :mod:`hitops.weather.build_extract`, described in
``hitops/weather/data/PROVENANCE.md``):

* 3-hourly: the instantaneous MERRA-2 analyses at 00, 03, ..., 21 UT of
  2018-04-07..13 for 10 sites (86 GHz native or derived, 230 GHz, 345 GHz
  scaled from the daily means, wind, PWV);
* daily: daily means for every day of all twelve months 2009-2018 for 8
  sites (230 GHz tabulated, 86 GHz derived on loading; 345 GHz tabulated in
  all 12 months; wind for 2009 only, none for November and December, where the
  nearest months' wind stands in: :func:`wind_pool`).

:func:`station_weather` turns a request (a date, or a month and a statistic)
into zenith opacity, sky brightness temperature and wind speed per band on
the observation's time grid, and says in one line which data it used.
"""

from __future__ import annotations

import csv
import datetime as dt
import difflib
import gzip
import importlib.resources
import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import InputError
from .sites import PROXIES, SITES, distance_km, pressure_ratio, resolve

#: frequencies the tables give (GHz) and the column prefix of each
TABLE_BANDS = {86.0: "86", 230.0: "230", 345.0: "345"}
#: a scene band within this fraction of a tabulated frequency uses that column
BAND_TOLERANCE = 0.05
STATISTICS = ("mean", "median", "good", "bad")
#: percentiles of the statistics 'good' and 'bad' (ngehtsim's convention: +-1 sigma)
PERCENTILES = {"good": 15.87, "bad": 84.13, "median": 50.0}
SEGMENT_HOURS = 3.0
MJD_EPOCH = dt.date(1858, 11, 17)
CLIMATOLOGY_HALF_WIDTH_DAYS = 3
#: a wind below this (m/s) is treated as this: t_c = r0 / v stays finite
MIN_WIND = 0.1
#: the shipped daily-mean table (gzip-compressed CSV, see build_extract.py)
DAILY_FILE = "merra2_daily.csv.gz"


class WeatherError(InputError):
    """A weather request the tables cannot answer (site, date, month or band)."""


@dataclass
class StationWeather:
    """Weather of one station on a time grid."""

    station: str
    site: str                                   # folder whose values were used
    mode: str                                   # '3-hourly', 'daily', 'climatology', 'month'
    description: str                            # one line: which data, which fallback
    tau: Dict[str, np.ndarray] = field(default_factory=dict)   # band name -> zenith opacity (n_time,)
    tb: Dict[str, np.ndarray] = field(default_factory=dict)    # band name -> zenith sky temperature (K)
    wind: Optional[np.ndarray] = None           # m/s (n_time,)
    source_columns: Dict[str, str] = field(default_factory=dict)  # band -> native/derived/scaled


# ----------------------------------------------------------------------------- loading

def _read_csv(name: str) -> List[dict]:
    """Rows of a shipped table; a ``.gz`` name is gzip-compressed CSV (read with the stdlib)."""
    resource = importlib.resources.files("hitops.weather").joinpath("data", name)
    if name.endswith(".gz"):
        text = gzip.decompress(resource.read_bytes()).decode("ascii")
    else:
        text = resource.read_text()
    return list(csv.DictReader(text.splitlines()))


@lru_cache(maxsize=None)
def model_86ghz() -> Dict[str, float]:
    """The fitted 86 GHz model (a, b, c of ``derivation_86ghz.json``)."""
    text = importlib.resources.files("hitops.weather").joinpath(
        "data", "derivation_86ghz.json").read_text()
    d = json.loads(text)
    return {"a": float(d["a"]), "b": float(d["b"]), "c": float(d["c"])}


def derive_86ghz(site: str, tau230, tb230):
    """Derived 86 GHz zenith opacity and sky temperature from the 230 GHz values of a site.

    ``tau86 = a (P/P0)^2 + b tau230`` (dry oxygen term scaling with the square of the
    surface pressure, P/P0 = exp(-h / 8 km), plus a wet term proportional to the 230 GHz
    opacity), ``Tb86 = c Tb230 / (1 - exp(-tau230)) (1 - exp(-tau86))``; see
    ``hitops/weather/data/PROVENANCE.md``.
    """
    m = model_86ghz()
    tau230 = np.asarray(tau230, dtype=np.float64)
    tb230 = np.asarray(tb230, dtype=np.float64)
    x2 = pressure_ratio(SITES[site]) ** 2
    tau86 = m["a"] * x2 + m["b"] * tau230
    tb86 = m["c"] * tb230 / -np.expm1(-tau230) * -np.expm1(-tau86)
    return tau86, tb86


def _num(value: str) -> float:
    return float(value) if value not in ("", None) else math.nan


def mjd_seconds(date: dt.date, hours: float = 0.0) -> float:
    return ((date - MJD_EPOCH).days + hours / 24.0) * 86400.0


@lru_cache(maxsize=None)
def native_table() -> Dict[str, Dict[str, np.ndarray]]:
    """site -> columns of the 3-hourly table, time-ordered; 'time' in MJD seconds (UTC)."""
    out: Dict[str, Dict[str, list]] = {}
    for row in _read_csv("merra2_3hourly.csv"):
        cols = out.setdefault(row["site"], {k: [] for k in (
            "time", "tau86", "tb86", "tau230", "tb230", "tau345", "tb345", "wind", "pwv",
            "src86", "src345")})
        date = dt.date(int(row["year"]), int(row["month"]), int(row["day"]))
        cols["time"].append(mjd_seconds(date, SEGMENT_HOURS * int(row["segment"])))
        for key in ("tau86", "tb86", "tau230", "tb230", "tau345", "tb345", "wind", "pwv"):
            cols[key].append(_num(row[key]))
        cols["src86"].append(row["src86"])
        cols["src345"].append(row["src345"])
    table = {}
    for site, cols in out.items():
        order = np.argsort(cols["time"])
        table[site] = {k: np.asarray(v)[order] for k, v in cols.items()}
    return table


@lru_cache(maxsize=None)
def daily_table() -> Dict[str, Dict[str, np.ndarray]]:
    """site -> columns of the daily table; 'date' as datetime.date.

    86 GHz values that are not native (``src86 == 'derived'``) are computed here from the
    230 GHz values with :func:`derive_86ghz` (the file stores only tabulated values).
    """
    out: Dict[str, Dict[str, list]] = {}
    for row in _read_csv(DAILY_FILE):
        cols = out.setdefault(row["site"], {k: [] for k in (
            "date", "tau86", "tb86", "tau230", "tb230", "tau345", "tb345", "wind", "src86")})
        cols["date"].append(dt.date(int(row["year"]), int(row["month"]), int(row["day"])))
        for key in ("tau86", "tb86", "tau230", "tb230", "tau345", "tb345", "wind"):
            cols[key].append(_num(row[key]))
        cols["src86"].append(row["src86"])
    table = {}
    for site, cols in out.items():
        order = np.argsort(np.array([d.toordinal() for d in cols["date"]]))
        columns = {k: (np.asarray(v, dtype=object) if k in ("date", "src86") else np.asarray(v))[order]
                   for k, v in cols.items()}
        derived = columns["src86"] == "derived"
        tau86, tb86 = derive_86ghz(site, columns["tau230"][derived], columns["tb230"][derived])
        columns["tau86"][derived] = tau86
        columns["tb86"][derived] = tb86
        table[site] = columns
    return table


def sites_with_tables() -> List[str]:
    return sorted(set(native_table()) | set(daily_table()))


# ----------------------------------------------------------------------------- resolution

def resolve_site(name: str, station: str = "") -> Tuple[str, str]:
    """(folder with tables, note) for a station code or folder name; WeatherError if unknown."""
    who = f"station {station}" if station else "weather"
    site = resolve(name)
    available = sites_with_tables()
    if site is None:
        codes = sorted({SITES[f].code for f in available} | set(available))
        near = difflib.get_close_matches(str(name).upper(), codes, n=1, cutoff=0.0)
        raise WeatherError(
            f"{who}: unknown merra2 site '{name}'; sites with tables: "
            f"{', '.join(f'{f} ({SITES[f].code})' for f in available)}; nearest name: {near[0]}")
    folder = site.folder
    if folder in available:
        return folder, ""
    proxy = PROXIES.get(folder)
    if proxy in available:
        km = distance_km(site, SITES[proxy])
        return proxy, (f"{folder} has no tables; using {proxy} ({SITES[proxy].name}, "
                       f"{km:.0f} km away) instead")
    nearest = min(available, key=lambda f: distance_km(site, SITES[f]))
    raise WeatherError(f"{who}: site {folder} ({site.code}) has no merra2 tables in the shipped "
                       f"extract; nearest site with tables: {nearest} ({SITES[nearest].code}); "
                       f"give weather: {{site: {nearest}}} to use it, or give tau and "
                       "coherence_time explicitly")


def band_column(freq_hz: float, band_name: str, station: str, site: str) -> str:
    """Column prefix ('86', '230', '345') for a band frequency; WeatherError if none is close."""
    ghz = freq_hz / 1e9
    nearest = min(TABLE_BANDS, key=lambda f: abs(f - ghz))
    if abs(nearest - ghz) > BAND_TOLERANCE * nearest:
        raise WeatherError(
            f"station {station}: band '{band_name}' at {ghz:g} GHz is not in the merra2 tables "
            f"of site {site} (they give 86 GHz (derived where not native), 230 and 345 GHz); "
            f"nearest: {nearest:g} GHz; give tau and t_atm for this band explicitly")
    return TABLE_BANDS[nearest]


def _statistic(values: np.ndarray, statistic: str) -> float:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return math.nan
    if statistic == "mean":
        return float(np.mean(values))
    return float(np.percentile(values, PERCENTILES[statistic]))


def _month_rows(site: str, month: int) -> Optional[np.ndarray]:
    daily = daily_table().get(site)
    if daily is None:
        return None
    mask = np.array([d.month == month for d in daily["date"]])
    return mask if mask.any() else None


def months_with_data(site: str) -> List[int]:
    months = set()
    if site in daily_table():
        months |= {d.month for d in daily_table()[site]["date"]}
    if site in native_table():
        months |= {dt.date.fromordinal(int(t // 86400) + MJD_EPOCH.toordinal()).month
                   for t in native_table()[site]["time"]}
    return sorted(months)


def _all_dates(site: str) -> List[dt.date]:
    dates = set()
    if site in daily_table():
        dates |= set(daily_table()[site]["date"])
    if site in native_table():
        dates |= {dt.date.fromordinal(int(t // 86400) + MJD_EPOCH.toordinal())
                  for t in native_table()[site]["time"]}
    return sorted(dates)


def wind_samples(site: str, month: int) -> np.ndarray:
    """Every wind value of a site and month: 3-hourly analyses and daily means."""
    values = []
    nat = native_table().get(site)
    if nat is not None:
        months = np.array([dt.date.fromordinal(int(t // 86400) + MJD_EPOCH.toordinal()).month
                           for t in nat["time"]])
        values.append(nat["wind"][months == month])
    mask = _month_rows(site, month)
    if mask is not None:
        values.append(daily_table()[site]["wind"][mask])
    values = np.concatenate(values) if values else np.zeros(0)
    return values[np.isfinite(values)]


def wind_pool(site: str, month: int) -> Tuple[np.ndarray, List[int], str]:
    """Wind values for a site and month, falling back to the nearest months that have some.

    The source's daily-mean wind files hold 2009 only, and those of November and
    December are header-only (no rows): for such a month the values of the nearest
    months with wind (circular distance 1, then 2, ...) are pooled.  Returns
    (values, months used, a note for the log; '' when the month itself has wind).
    """
    values = wind_samples(site, month)
    if values.size:
        return values, [month], ""
    for distance in range(1, 7):
        near = sorted({(month - 1 + d) % 12 + 1 for d in (-distance, distance)})
        pooled = [wind_samples(site, m) for m in near]
        pooled = [v for v in pooled if v.size]
        if pooled:
            used = [m for m in near if wind_samples(site, m).size]
            note = (f"no wind in the source for month {month} at {site}; wind of month"
                    f"{'s' if len(used) > 1 else ''} {', '.join(map(str, used))} used")
            return np.concatenate(pooled), used, note
    return np.zeros(0), [], f"no wind in the tables for site {site}"


def parse_date(value) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    try:
        return dt.date.fromisoformat(str(value).strip()[:10])
    except ValueError as err:
        raise WeatherError(f"weather date {value!r} is not a date like 2023-04-10") from err


def station_weather(station: str, bands: Sequence[Tuple[str, float]], times: np.ndarray, *,
                    site: Optional[str] = None, date=None, year: Optional[int] = None,
                    month: Optional[int] = None, statistic: str = "median",
                    fallback: str = "climatology") -> StationWeather:
    """Zenith opacity, sky temperature per band and wind of a station on ``times`` (MJD s, UTC).

    ``date`` picks that day (3-hourly analyses interpolated linearly in time
    where the 3-hourly table covers the observation, else that day's daily
    means); ``year`` replaces the date's year (the same day of another year);
    where the date is not in the tables, ``fallback='climatology'`` uses the
    ``statistic`` of the daily means within +-3 days of that calendar day over
    all years, ``fallback='error'`` refuses.  Without a date, ``month`` and
    ``statistic`` (mean, median, good = 15.87th, bad = 84.13th percentile, per
    quantity) give constant values.
    """
    folder, note = resolve_site(site or station, station)
    if statistic not in STATISTICS:
        raise WeatherError(f"station {station}: weather statistic '{statistic}' is not one of "
                           f"{', '.join(STATISTICS)}")
    columns = {name: band_column(freq, name, station, folder) for name, freq in bands}
    times = np.asarray(times, dtype=np.float64)
    out = None
    if date is not None:
        wanted = parse_date(date)
        used = wanted
        if year is not None:
            try:
                used = wanted.replace(year=int(year))
            except ValueError:
                used = wanted.replace(year=int(year), day=28)
        # the observation's first UTC day is mapped onto the weather date
        first_day = dt.date.fromordinal(int(times.min() // 86400) + MJD_EPOCH.toordinal()) \
            if times.size else used
        shift = (used - first_day).days * 86400.0
        out = _from_native(station, folder, columns, times + shift, used, wanted)
        if out is None:
            out = _from_daily(station, folder, columns, times + shift, used, wanted)
        if out is None:
            if fallback != "climatology":
                raise _date_error(station, folder, used)
            out = _climatology(station, folder, columns, times, used, statistic)
    else:
        if month is None:
            raise WeatherError(f"station {station}: merra2 weather needs a date or a month")
        month = int(month)
        mask = _month_rows(folder, month)
        if mask is None:
            raise WeatherError(f"station {station}: no merra2 data for site {folder} in month "
                               f"{month}; months with data: "
                               f"{', '.join(map(str, months_with_data(folder)))}")
        winds, _, wind_note = wind_pool(folder, month)
        out = _constant(station, folder, columns, times, mask, statistic, "month", winds,
                        f"{statistic} of the daily means of month {month}, "
                        f"{_years(folder, mask)}", wind_note)
    if note:
        out.description = f"{out.description} ({note})"
    if date is not None:
        req_month = (used if out.mode != "climatology" else wanted).month
    else:
        req_month = month
    _check_finite(out, folder, req_month, columns)
    return out


def _years(folder: str, mask: np.ndarray) -> str:
    years = sorted({d.year for d in daily_table()[folder]["date"][mask]})
    return f"{years[0]}-{years[-1]}" if years else ""


def _date_error(station: str, folder: str, date: dt.date) -> WeatherError:
    dates = _all_dates(folder)
    same_day = [d for d in dates if (d.month, d.day) == (date.month, date.day)]
    if same_day:
        best = min(same_day, key=lambda d: abs(d.year - date.year))
        nearest = f"{best.isoformat()} (the same day of {best.year}: give year: {best.year})"
    elif dates:
        nearest = min(dates, key=lambda d: abs((d - date).days)).isoformat()
    else:
        nearest = "none"
    return WeatherError(
        f"station {station}: no merra2 data for site {folder} on {date.isoformat()} (the "
        f"shipped tables hold {dates[0].isoformat()}..{dates[-1].isoformat()}, "
        f"months {', '.join(map(str, months_with_data(folder)))}); nearest available date: "
        f"{nearest}")


def _check_finite(out: StationWeather, folder: str, month: Optional[int] = None,
                  columns: Optional[Dict[str, str]] = None) -> None:
    for name in out.tau:
        if not (np.all(np.isfinite(out.tau[name])) and np.all(np.isfinite(out.tb[name]))):
            have = _bands_with_data(folder)
            col = columns.get(name) if columns else None
            where = ""
            if col is not None and month is not None:
                months = _band_months(folder, col)
                here = _bands_with_data(folder, month)
                near = min(here, key=lambda c: abs(float(c) - float(col))) if here else None
                where = ((f"; band {col} GHz has data at {folder} only in months "
                          f"{', '.join(map(str, months))}" if months else
                          f"; band {col} GHz has no data at {folder} in any month")
                         + (f"; nearest band with data in month {month}: {near} GHz" if near else ""))
            raise WeatherError(
                f"station {out.station}: the merra2 tables have no values for band '{name}' at "
                f"site {folder} ({out.description}){where}; bands with data there in some month: "
                f"{', '.join(have)} GHz; give tau and t_atm for this band explicitly")


def _bands_with_data(folder: str, month: Optional[int] = None) -> List[str]:
    """Tabulated bands at a site (in a month, if given)."""
    have = []
    for col in TABLE_BANDS.values():
        if month in _band_months(folder, col) or (month is None and _band_months(folder, col)):
            have.append(col)
    return have


def _band_months(folder: str, col: str) -> List[int]:
    """Months in which a site has finite values of one band (3-hourly or daily)."""
    months = set()
    nat = native_table().get(folder)
    if nat is not None and np.isfinite(nat[f"tau{col}"]).any():
        months.add(4)                       # the 3-hourly analyses are April 2018
    day = daily_table().get(folder)
    if day is not None:
        ok = np.isfinite(day[f"tau{col}"])
        months.update(d.month for d in day["date"][ok])
    return sorted(months)


def _from_native(station, folder, columns, times, used, wanted) -> Optional[StationWeather]:
    nat = native_table().get(folder)
    if nat is None or times.size == 0:
        return None
    # every time must lie within the 3-hourly series (the edge analyses hold for
    # up to half a segment beyond it)
    half = SEGMENT_HOURS * 3600.0 / 2
    if times.min() < nat["time"][0] - half or times.max() > nat["time"][-1] + half:
        return None
    out = StationWeather(station, folder, "3-hourly", "")
    for name, col in columns.items():
        out.tau[name] = np.interp(times, nat["time"], nat[f"tau{col}"])
        out.tb[name] = np.interp(times, nat["time"], nat[f"tb{col}"])
        src = {"86": nat["src86"], "345": nat["src345"]}.get(col)
        out.source_columns[name] = (str(src[0]) if src is not None else "merra2_am")
    out.wind = np.interp(times, nat["time"], nat["wind"])
    subst = "" if used == wanted else f" (same day of {used.year} for {wanted.isoformat()})"
    out.description = (f"MERRA-2 3-hourly analyses of {used.isoformat()} at {folder}, "
                       f"linearly interpolated in time{subst}")
    return out


def _from_daily(station, folder, columns, times, used, wanted) -> Optional[StationWeather]:
    daily = daily_table().get(folder)
    if daily is None:
        return None
    ordinals = np.array([d.toordinal() for d in daily["date"]])
    day_of = (times // 86400).astype(np.int64) + MJD_EPOCH.toordinal()
    index = np.searchsorted(ordinals, day_of)
    index = np.clip(index, 0, ordinals.size - 1)
    if not np.all(ordinals[index] == day_of):
        return None
    out = StationWeather(station, folder, "daily", "")
    for name, col in columns.items():
        out.tau[name] = daily[f"tau{col}"][index].astype(np.float64)
        out.tb[name] = daily[f"tb{col}"][index].astype(np.float64)
        out.source_columns[name] = "derived" if col == "86" else "merra2_am"
    wind = daily["wind"][index].astype(np.float64)
    wind_note = ""
    if not np.all(np.isfinite(wind)):
        pool, months, fallback = wind_pool(folder, used.month)
        clim = _statistic(pool, "median")
        wind = np.where(np.isfinite(wind), wind, clim)
        wind_note = (f"; wind: median of the site's month-{'/'.join(map(str, months))} values "
                     f"({clim:.1f} m/s){' (' + fallback + ')' if fallback else ''}")
    out.wind = wind
    subst = "" if used == wanted else f" (same day of {used.year} for {wanted.isoformat()})"
    out.description = f"MERRA-2 daily means of {used.isoformat()} at {folder}{subst}{wind_note}"
    return out


def _climatology(station, folder, columns, times, date, statistic) -> StationWeather:
    daily = daily_table().get(folder)
    if daily is None or _month_rows(folder, date.month) is None:
        raise _date_error(station, folder, date)
    doy = np.array([(d - dt.date(d.year, date.month, 1)).days if d.month == date.month else 999
                    for d in daily["date"]])
    target = (date - dt.date(date.year, date.month, 1)).days
    mask = np.abs(doy - target) <= CLIMATOLOGY_HALF_WIDTH_DAYS
    if not mask.any():
        raise _date_error(station, folder, date)
    wind = [daily["wind"][mask]]
    wind_note = ""
    nat = native_table().get(folder)
    if nat is not None:
        nat_dates = [dt.date.fromordinal(int(t // 86400) + MJD_EPOCH.toordinal()) for t in nat["time"]]
        near = np.array([d.month == date.month and abs(d.day - date.day) <= CLIMATOLOGY_HALF_WIDTH_DAYS
                         for d in nat_dates])
        wind.append(nat["wind"][near])
    wind = np.concatenate(wind)
    if not np.isfinite(wind).any():
        wind, _, wind_note = wind_pool(folder, date.month)
    return _constant(station, folder, columns, times, mask, statistic, "climatology", wind,
                     f"{date.isoformat()} is not in the tables: {statistic} of the daily means of "
                     f"{date.strftime('%m-%d')} +-{CLIMATOLOGY_HALF_WIDTH_DAYS} d over "
                     f"{_years(folder, mask)} at {folder} (climatology)", wind_note)


def _constant(station, folder, columns, times, mask, statistic, mode, wind_values,
              description, wind_note: str = "") -> StationWeather:
    daily = daily_table()[folder]
    out = StationWeather(station, folder, mode, description)
    for name, col in columns.items():
        out.tau[name] = np.full(times.shape, _statistic(daily[f"tau{col}"][mask], statistic))
        out.tb[name] = np.full(times.shape, _statistic(daily[f"tb{col}"][mask], statistic))
        out.source_columns[name] = "derived" if col == "86" else "merra2_am"
    wind_values = np.asarray(wind_values, dtype=np.float64)
    wind = _statistic(wind_values, statistic)
    out.wind = np.full(times.shape, wind)
    out.description += (f"; wind {statistic} {wind:.1f} m/s of {np.isfinite(wind_values).sum()} values "
                        "(2009 daily means, 2018 analyses: other years have no wind in the extract"
                        f"{'; ' + wind_note if wind_note else ''})")
    return out


def effective_temperature(tau: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """T_atm such that T_atm (1 - exp(-tau)) = Tb: the sky temperature at any airmass follows."""
    tau = np.asarray(tau, dtype=np.float64)
    return np.where(tau > 0, np.asarray(tb) / -np.expm1(-np.maximum(tau, 1e-12)), 270.0)
