"""``forecast(...)``: how often 86 GHz phase-wrap counting fails, per baseline and month.

Steps: station parameters (catalogue) -> weather samples per station and month
(every 3-hourly analysis and every daily mean of the tables) -> baselines: the
samples both sites share (same year, day and analysis) -> per-sample SNR and
coherence time at the chosen elevation -> slip probability per hour (naive
counting exact, smoothed tracker bounded; :mod:`hitops.forecast.model`) ->
table, markdown, JSON and a station x month heat map.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import logging
import time as _time
from pathlib import Path
from typing import Dict, List

import numpy as np

from ..errors import InputError, OutputExistsError
from ..weather import tables as wt
from ..weather.sites import SITES
from . import model

log = logging.getLogger("hitops.forecast")

PAPER_STATIONS = ("AP", "SM", "PV", "GL", "PB", "KP", "KC", "KY")
#: 86 GHz parameters of sites in the tables that the station catalogue lacks: ASSUMED
#: (JC: the paper's JCMT-at-86 values; LM: LMT 50 m 3 mm; AZ: SMT 10 m, hypothetical 3 mm receiver)
EXTRA_STATIONS = {
    "JC": {"diameter": 15.0, "t_rx": 70.0, "aperture_efficiency": 0.60},
    "LM": {"diameter": 50.0, "t_rx": 70.0, "aperture_efficiency": 0.35},
    "AZ": {"diameter": 10.0, "t_rx": 60.0, "aperture_efficiency": 0.60},
}
MONTH_NAMES = ["Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec"]
QUANTILES = (15.87, 50.0, 84.13)


def _station_params(code: str) -> Dict[str, float]:
    from ..simulate.scene import _catalogue

    cat = _catalogue()
    if code in cat:
        band = cat[code]["bands"]["86"]
        return {"diameter": float(cat[code]["diameter"]), "t_rx": float(band["t_rx"]),
                "aperture_efficiency": float(band.get("aperture_efficiency", 0.5))}
    return dict(EXTRA_STATIONS[code])


def parse_stations(stations: str) -> List[str]:
    text = str(stations).strip()
    if text.lower() == "paper":
        return list(PAPER_STATIONS)
    if text.lower() == "all":
        return list(PAPER_STATIONS) + list(EXTRA_STATIONS)
    codes = [c.strip().upper() for c in text.split(",") if c.strip()]
    known = list(PAPER_STATIONS) + list(EXTRA_STATIONS)
    for code in codes:
        if code not in known:
            wt.resolve_site(code, code)          # unknown site: names the nearest
            raise InputError(f"forecast: station {code} has tables but no 86 GHz receiver "
                             f"parameters; known stations: {', '.join(known)}")
    if len(codes) < 2:
        raise InputError(f"forecast: give at least two stations (got {codes}); known: "
                         f"{', '.join(known)}")
    return codes


def parse_months(months: str) -> List[int] | None:
    text = str(months).strip().lower()
    if text == "all":
        return None
    out = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-"))
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
        except ValueError as err:
            raise InputError(f"forecast: months must be numbers 1-12 or ranges like 3-5, "
                             f"got {part!r}") from err
    bad = [m for m in out if not 1 <= m <= 12]
    if bad or not out:
        raise InputError(f"forecast: months must lie in 1-12, got {months!r}")
    return sorted(set(out))


def station_samples(code: str, month: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
    """Weather samples of a station in a month, keyed (year, day, analysis; -1 = daily mean).

    Daily means without a tabulated wind take a wind drawn from the site's other
    wind values of that month (wind assumed independent of opacity there), or of the
    nearest months with wind where the month has none (November, December:
    :func:`hitops.weather.tables.wind_pool`).
    """
    folder, _ = wt.resolve_site(code, code)
    keys, tau, tb, wind = [], [], [], []
    nat = wt.native_table().get(folder)
    if nat is not None:
        for i, t in enumerate(nat["time"]):
            day = dt.date.fromordinal(int(t // 86400) + wt.MJD_EPOCH.toordinal())
            if day.month == month:
                keys.append((day.year, day.day, int(round((t % 86400) / 10800))))
                tau.append(nat["tau86"][i])
                tb.append(nat["tb86"][i])
                wind.append(nat["wind"][i])
    daily = wt.daily_table().get(folder)
    if daily is not None:
        for i, day in enumerate(daily["date"]):
            if day.month == month:
                keys.append((day.year, day.day, -1))
                tau.append(daily["tau86"][i])
                tb.append(daily["tb86"][i])
                wind.append(daily["wind"][i])
    wind = np.array(wind, dtype=np.float64)
    missing = ~np.isfinite(wind)
    if missing.any():
        pool = wind[~missing]
        if not pool.size:
            # no wind in the source for this month (November, December): nearest months'
            pool, _, _ = wt.wind_pool(folder, month)
        wind[missing] = rng.choice(pool, size=int(missing.sum())) if pool.size else 5.0
    return {"keys": keys, "tau": np.array(tau), "tb": np.array(tb), "wind": wind}


def forecast(stations="all", months="all", elevation=30.0, flux=1.1, bandwidth=2.0,
             integration=1.0, r0=100.0, outdir="forecast", prefix="forecast",
             overwrite=False, no_plot=False) -> Dict:
    """Slip probabilities of 86 GHz wrap counting per baseline and month; see the module doc.

    Returns the JSON payload (also written to OUTDIR/PREFIX.json).
    """
    t0 = _time.perf_counter()
    codes = parse_stations(stations)
    wanted = parse_months(months)
    for name, value, lo, hi in (("elevation", elevation, 1.0, 90.0), ("flux", flux, 1e-6, 1e6),
                                ("bandwidth", bandwidth, 1e-6, 1e3),
                                ("integration", integration, 1e-3, 1e4), ("r0", r0, 1e-3, 1e6)):
        if not (isinstance(value, (int, float)) and lo <= float(value) <= hi):
            raise InputError(f"forecast: {name} must lie in [{lo:g}, {hi:g}], got {value!r}")
    folders = {c: wt.resolve_site(c, c)[0] for c in codes}
    available = {c: wt.months_with_data(folders[c]) for c in codes}
    if wanted is None:
        month_list = sorted(set().union(*available.values()))
    else:
        month_list = wanted
        for c in codes:
            missing = [m for m in wanted if m not in available[c]]
            if missing:
                raise InputError(
                    f"forecast: no merra2 data for station {c} (site {folders[c]}) in month "
                    f"{missing[0]}; months with data there: "
                    f"{', '.join(map(str, available[c])) or 'none'}")
    outdir = Path(outdir)
    paths = {k: outdir / f"{prefix}{s}" for k, s in (("csv", ".csv"), ("md", ".md"),
                                                       ("json", ".json"), ("png", "-heatmap.png"))}
    if no_plot:
        paths.pop("png")
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} exist(s); pass --overwrite or choose "
                                "another --outdir/--prefix")

    dt_s, bw = float(integration), float(bandwidth) * 1e9
    model.failure_table()
    rows = []
    rng = np.random.default_rng(86)
    params = {c: _station_params(c) for c in codes}
    for month in month_list:
        samples = {}
        for c in codes:
            if month not in available[c]:
                log.warning("forecast: station %s (site %s) has no data in month %d; skipped",
                            c, folders[c], month)
                continue
            s = station_samples(c, month, rng)
            p = params[c]
            s["sefd"] = model.sefd_86(p["t_rx"], p["aperture_efficiency"], p["diameter"],
                                      s["tau"], s["tb"], elevation)
            s["tc"] = model.station_coherence_86(s["wind"], r0, elevation)
            s["index"] = {k: i for i, k in enumerate(s["keys"])}
            samples[c] = s
        present = [c for c in codes if c in samples]
        for a in range(len(present)):
            for b in range(a + 1, len(present)):
                p, q = samples[present[a]], samples[present[b]]
                shared = [k for k in p["keys"] if k in q["index"]]
                if not shared:
                    continue
                ip = np.array([p["index"][k] for k in shared])
                iq = np.array([q["index"][k] for k in shared])
                rho, sigma, tc_bl = model.baseline_terms(flux, bw, dt_s, p["sefd"][ip],
                                                         q["sefd"][iq], p["tc"][ip], q["tc"][iq])
                p_naive = model.naive_failure_probability(rho, sigma)
                # the smoothed tracker's bound is loose at high SNR: never above naive counting
                p_smooth = np.minimum(model.smooth_slip_probability(rho, tc_bl, dt_s), p_naive)
                naive = model.per_hour(p_naive, dt_s)
                smooth = model.per_hour(p_smooth, dt_s)
                fail_rate = p_naive * 3600.0 / dt_s
                rq, tq = np.percentile(rho, QUANTILES), np.percentile(tc_bl, QUANTILES)
                rows.append({
                    "baseline": f"{present[a]}-{present[b]}", "month": month,
                    "n_samples": len(shared),
                    "rho_p16": rq[0], "rho_median": rq[1], "rho_p84": rq[2],
                    "tc86_p16": tq[0], "tc86_median": tq[1], "tc86_p84": tq[2],
                    "naive_failures_per_hour_mean": float(np.mean(fail_rate)),
                    "naive_p_hour_mean": float(np.mean(naive)),
                    "naive_p_hour_median": float(np.median(naive)),
                    "smooth_p_hour_mean_bound": float(np.mean(smooth)),
                })
    if not rows:
        raise InputError(f"forecast: no baseline of {', '.join(codes)} shares data in months "
                         f"{month_list}")
    summary = station_month_summary(rows, codes, month_list)
    payload = {
        "inputs": {"stations": codes, "months": month_list, "elevation": elevation, "flux": flux,
                   "bandwidth_ghz": bandwidth, "integration": integration, "r0": r0},
        "sites": {c: folders[c] for c in codes},
        "baselines": rows, "stations": summary,
    }
    outdir.mkdir(parents=True, exist_ok=True)
    _write_csv(paths["csv"], rows)
    paths["md"].write_text(markdown(payload))
    paths["json"].write_text(json.dumps(payload, indent=1) + "\n")
    if "png" in paths:
        heatmap(summary, codes, paths["png"], elevation, flux)
    log.info("forecast: %d stations, %d months, %d baseline-months in %.1f s -> %s", len(codes),
             len(month_list), len(rows), _time.perf_counter() - t0, paths["csv"])
    return payload


def station_month_summary(rows, codes, months) -> Dict[str, Dict[str, float]]:
    """Per station and month: the median over its baselines of the mean naive P(miss)/hour."""
    out = {}
    for c in codes:
        out[c] = {}
        for m in months:
            vals = [r["naive_p_hour_mean"] for r in rows if r["month"] == m
                    and c in r["baseline"].split("-")]
            smooth = [r["smooth_p_hour_mean_bound"] for r in rows if r["month"] == m
                      and c in r["baseline"].split("-")]
            if vals:
                out[c][str(m)] = {"naive_p_hour": float(np.median(vals)),
                                  "smooth_p_hour_bound": float(np.median(smooth))}
    return out


def _write_csv(path: Path, rows) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})


def markdown(payload) -> str:
    inp = payload["inputs"]
    lines = [f"# FPT forecast: 86 GHz wrap counting, elevation {inp['elevation']:g} deg, "
             f"{inp['flux']:g} Jy, {inp['bandwidth_ghz']:g} GHz, {inp['integration']:g} s", "",
             "| baseline | month | samples | rho p16/50/84 | t_c 86 GHz (s) p16/50/84 | "
             "naive failures/h (mean) | P(naive misses a wrap in 1 h), mean | median | "
             "smooth tracker, bound |", "|---|---|---|---|---|---|---|---|---|"]
    for r in payload["baselines"]:
        lines.append(
            f"| {r['baseline']} | {MONTH_NAMES[r['month'] - 1]} | {r['n_samples']} | "
            f"{r['rho_p16']:.1f} / {r['rho_median']:.1f} / {r['rho_p84']:.1f} | "
            f"{r['tc86_p16']:.1f} / {r['tc86_median']:.1f} / {r['tc86_p84']:.1f} | "
            f"{r['naive_failures_per_hour_mean']:.3g} | {r['naive_p_hour_mean']:.3g} | "
            f"{r['naive_p_hour_median']:.3g} | {r['smooth_p_hour_mean_bound']:.3g} |")
    return "\n".join(lines) + "\n"


def heatmap(summary, codes, path: Path, elevation, flux) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    grid = np.full((len(codes), 12), np.nan)
    for i, c in enumerate(codes):
        for m, v in summary.get(c, {}).items():
            grid[i, int(m) - 1] = max(v["naive_p_hour"], 1e-6)
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(codes) + 1.6))
    cmap = plt.get_cmap("viridis").copy()
    cmap.set_bad("0.85")
    im = ax.imshow(np.ma.masked_invalid(grid), cmap=cmap, norm=LogNorm(1e-6, 1.0), aspect="auto")
    for i in range(len(codes)):
        for m in range(12):
            if np.isfinite(grid[i, m]):
                ax.text(m, i, f"{grid[i, m]:.1g}", ha="center", va="center", fontsize=7,
                        color="white" if grid[i, m] < 1e-2 else "black")
    ax.set_xticks(range(12), MONTH_NAMES)
    ax.set_yticks(range(len(codes)), codes)
    ax.set_title(f"P(naive PWC misses an 86 GHz wrap within 1 h), median over baselines\n"
                 f"elevation {elevation:g} deg, {flux:g} Jy (grey: no data in the extract)",
                 fontsize=9)
    fig.colorbar(im, ax=ax, label="probability per hour")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
