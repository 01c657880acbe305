"""Build the shipped MERRA-2 weather extract (hitops/weather/data/) from the source rows.

    python -m hitops.weather.build_extract          # numpy only, no network

Inputs: ``hitops/weather/sources/`` holds verbatim line copies of the public
ngEHT weather tables (Smithsonian/ngeht-weather and the older text copy inside
Smithsonian/ngehtsim), with a manifest naming repository, path and commit of
every file (``sources/native/manifest_native.tsv``, ``sources/daily/manifest.tsv``):

* ``native/<SITE>/04Apr/``: 3-hourly rows (MERRA-2 analysis times 00, 03, ..., 21 UT)
  for 2018-04-06..14: ``SEFD_info_230.csv`` (tau, Tb at 230 GHz), ``SEFD_info_86.csv``
  (86 GHz, APEX and KVNYS only), ``wind_speed.csv``, ``PWV.csv``;
  ``GLT/04Apr/mean_SEFD_info_86.csv``: GLT daily means at 86 GHz, April 2018.
* ``daily/<SITE>/<MM><Mon>/`` (one folder per month, e.g. ``03Mar``, ``04Apr``, named as in
  the source): daily means (mean of the 8 analyses) for 2009-2018:
  ``mean_SEFD_info_230.csv``, ``mean_SEFD_info_345.csv``, ``mean_wind_speed.csv`` (2009 only);
  a month folder may lack the 345 GHz or wind file (those columns are then empty).

Outputs (``hitops/weather/data/``):

* ``merra2_3hourly.csv``: one row per site, day (2018-04-07..13) and analysis time.
* ``merra2_daily.csv.gz``: one row per site and day (every month folder in ``sources/daily``),
  gzip-compressed CSV (stdlib ``gzip``; header mtime 0, so a rebuild is byte-identical).
  Tabulated values are written as the shortest text that reads back to the same float
  (exact); derived 86 GHz values are NOT stored: ``tau86``/``tb86`` are filled only where
  native (``src86 = merra2_am``), and :mod:`hitops.weather.tables` computes the derived ones
  on loading from the fitted model in ``derivation_86ghz.json`` (this keeps 12 months of
  8 sites well under the 1 MB budget of the data folder).
* ``derivation_86ghz.json``: the fitted 86 GHz model, its errors, the 345 GHz scaling.

How the bands the tables lack are filled (column ``src86`` / ``src345``):

* 86 GHz: native where tabulated (``merra2_am``); elsewhere ``derived``:
  ``tau86 = a (P/P0)^2 + b tau230`` (a dry, oxygen term that scales with the
  square of the surface pressure, P/P0 = exp(-h / 8 km), plus a wet term
  proportional to the 230 GHz opacity, which water vapour dominates) and
  ``Tb86 = c T_eff,230 (1 - exp(-tau86))`` with ``T_eff,230 = Tb230 / (1 - exp(-tau230))``.
  a, b, c are fitted (weighted least squares) to every native 86 GHz value in the
  sources: APEX and KVNYS 3-hourly, GLT daily means (weight 8, one day of analyses).
* 345 GHz in the 3-hourly table: each analysis's 230 GHz opacity times that day's
  ratio of the daily means tau345 / tau230 (``scaled_daily``), the brightness
  from the daily mean's effective temperature; the mean over a day's 8 analyses
  then equals the tabulated daily mean.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import math
from pathlib import Path

import numpy as np

from .sites import SITES, pressure_ratio

HERE = Path(__file__).resolve().parent
SOURCES = HERE / "sources"
DATA = HERE / "data"
YEAR, MONTH = 2018, 4
NATIVE_DAYS = range(7, 14)          # every site has all 8 analyses of these days
SEGMENTS = range(8)
DAILY_FILE = "merra2_daily.csv.gz"


def _rows(path: Path):
    """Numeric rows of a source file (header boxes and column-name lines skipped)."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#") or not line[0].isdigit():
            continue
        out.append([p.strip() for p in line.split(",")])
    return out


def read_native(path: Path, n_values: int):
    """{(day, segment): [values]} of a 3-hourly file in either source layout.

    Layouts: ``year,month,day,segment,v...`` or (older 230 GHz files)
    ``year,day,segment,v...``; told apart by the number of columns.
    """
    out = {}
    for f in _rows(path):
        if len(f) == 4 + n_values:
            year, day, seg, vals = int(f[0]), int(f[2]), int(f[3]), f[4:]
        elif len(f) == 3 + n_values:
            year, day, seg, vals = int(f[0]), int(f[1]), int(f[2]), f[3:]
        else:
            raise ValueError(f"{path}: unexpected row {f}")
        if year != YEAR:
            raise ValueError(f"{path}: year {year}, expected {YEAR}")
        if (day, seg) in out:
            raise ValueError(f"{path}: duplicate row {(day, seg)}")
        out[(day, seg)] = [float(v) for v in vals]
    return out


def read_daily(path: Path, n_values: int):
    """{(year, day): [values]} of a daily-mean file (``year,[month,]day,v...``)."""
    out = {}
    for f in _rows(path):
        if len(f) == 3 + n_values:
            year, day, vals = int(f[0]), int(f[2]), f[3:]
        elif len(f) == 2 + n_values:
            year, day, vals = int(f[0]), int(f[1]), f[2:]
        else:
            raise ValueError(f"{path}: unexpected row {f}")
        out[(year, day)] = [float(v) if v.lower() != "nan" else math.nan for v in vals]
    return out


def load_sources():
    native, daily = {}, {}
    for site_dir in sorted((SOURCES / "native").iterdir()):
        d = site_dir / "04Apr"
        if not d.is_dir():
            continue
        native[site_dir.name] = {
            "230": read_native(d / "SEFD_info_230.csv", 2),
            "86": read_native(d / "SEFD_info_86.csv", 2),
            "wind": read_native(d / "wind_speed.csv", 1),
            "pwv": read_native(d / "PWV.csv", 1),
            "86daily": {k[1]: v for k, v in read_daily(d / "mean_SEFD_info_86.csv", 2).items()},
        }
    for site_dir in sorted((SOURCES / "daily").iterdir()):
        if not site_dir.is_dir():
            continue
        q = {"230": {}, "345": {}, "wind": {}}
        # one folder per month, named as in the source (01Jan, 02Feb, ..., 12Dec)
        for d in sorted(p for p in site_dir.iterdir() if p.is_dir() and p.name[:2].isdigit()):
            month = int(d.name[:2])
            for band, name, n in (("230", "mean_SEFD_info_230.csv", 2),
                                  ("345", "mean_SEFD_info_345.csv", 2),
                                  ("wind", "mean_wind_speed.csv", 1)):
                for (year, day), vals in read_daily(d / name, n).items():
                    q[band][(year, month, day)] = vals
        if q["230"]:
            daily[site_dir.name] = q
    return native, daily


# ----------------------------------------------------------------------------- 86 GHz model

def calibration_points(native):
    """(site, (P/P0)^2, tau230, Tb230, tau86, Tb86, weight) for every native 86 GHz value."""
    pts = []
    for site, q in native.items():
        x2 = pressure_ratio(SITES[site]) ** 2
        if q["86"]:
            for key, (t86, tb86) in q["86"].items():
                if key in q["230"] and key[0] in NATIVE_DAYS:
                    t230, tb230 = q["230"][key]
                    pts.append((site, x2, t230, tb230, t86, tb86, 1.0))
        for day, (t86, tb86) in q["86daily"].items():
            segs = [q["230"].get((day, s)) for s in SEGMENTS]
            if day in NATIVE_DAYS and all(segs):
                t230 = float(np.mean([s[0] for s in segs]))
                tb230 = float(np.mean([s[1] for s in segs]))
                pts.append((site, x2, t230, tb230, t86, tb86, 8.0))
    return pts


def fit_86(pts):
    """Weighted least squares for (a, b) of tau86 = a x2 + b tau230, then c of Tb86."""
    x2 = np.array([p[1] for p in pts])
    t230 = np.array([p[2] for p in pts])
    tb230 = np.array([p[3] for p in pts])
    t86 = np.array([p[4] for p in pts])
    tb86 = np.array([p[5] for p in pts])
    w = np.array([p[6] for p in pts])
    sw = np.sqrt(w)
    design = np.stack([x2, t230], axis=1)
    (a, b), *_ = np.linalg.lstsq(design * sw[:, None], t86 * sw, rcond=None)
    shape = tb230 / -np.expm1(-t230) * -np.expm1(-t86)
    c = float(np.sum(w * shape * tb86) / np.sum(w * shape * shape))
    return float(a), float(b), c


def tau86_model(x2, tau230, a, b):
    return a * x2 + b * tau230


def tb86_model(tau230, tb230, tau86, c):
    return c * tb230 / -np.expm1(-tau230) * -np.expm1(-tau86)


def validate_86(pts, params):
    """Median |fractional error| per site, in-sample and leaving that site out of the fit."""
    out = {}
    for site in sorted({p[0] for p in pts}):
        mine = [p for p in pts if p[0] == site]
        others = [p for p in pts if p[0] != site]
        result = {"n_points": len(mine)}
        for label, (a, b, c) in (("all_sites_fit", params), ("leave_site_out", fit_86(others))):
            tau = np.array([tau86_model(p[1], p[2], a, b) for p in mine])
            tb = np.array([tb86_model(p[2], p[3], t, c) for p, t in zip(mine, tau)])
            t_pub = np.array([p[4] for p in mine])
            tb_pub = np.array([p[5] for p in mine])
            result[label] = {
                "median_abs_frac_err_tau86": round(float(np.median(np.abs(tau / t_pub - 1))), 3),
                "median_signed_frac_err_tau86": round(float(np.median(tau / t_pub - 1)), 3),
                "median_abs_frac_err_tb86": round(float(np.median(np.abs(tb / tb_pub - 1))), 3),
                "published_tau86_median": round(float(np.median(t_pub)), 4),
                "model_tau86_median": round(float(np.median(tau)), 4),
            }
        out[site] = result
    return out


# ----------------------------------------------------------------------------- tables

def _f(x):
    """A tabulated value as the shortest text that reads back to the same float (exact)."""
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else repr(float(x))


def _d(x):
    """A derived value, to 6 significant digits (the derivation is good to ~5-30 %)."""
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.6g}"


def build():
    native, daily = load_sources()
    pts = calibration_points(native)
    a, b, c = fit_86(pts)
    params = (a, b, c)

    rows3 = []
    for site in sorted(native):
        q = native[site]
        x2 = pressure_ratio(SITES[site]) ** 2
        for day in NATIVE_DAYS:
            d345 = daily.get(site, {}).get("345", {}).get((YEAR, MONTH, day))
            d230 = daily.get(site, {}).get("230", {}).get((YEAR, MONTH, day))
            for seg in SEGMENTS:
                key = (day, seg)
                if key not in q["230"] or key not in q["wind"]:
                    raise ValueError(f"{site}: no 230 GHz or wind row for 2018-04-{day} segment {seg}")
                tau230, tb230 = q["230"][key]
                if key in q["86"]:
                    (tau86, tb86), src86 = q["86"][key], "merra2_am"
                else:
                    tau86 = tau86_model(x2, tau230, a, b)
                    tb86, src86 = tb86_model(tau230, tb230, tau86, c), "derived"
                if d345 and d230:
                    tau345 = tau230 * d345[0] / d230[0]
                    tb345 = d345[1] / -math.expm1(-d345[0]) * -math.expm1(-tau345)
                    src345 = "scaled_daily"
                else:
                    tau345 = tb345 = None
                    src345 = ""
                pwv = q["pwv"].get(key, [None])[0]
                fmt86 = _f if src86 == "merra2_am" else _d
                rows3.append([site, YEAR, MONTH, day, seg, fmt86(tau86), fmt86(tb86), src86,
                              _f(tau230), _f(tb230), _d(tau345), _d(tb345), src345,
                              _f(q["wind"][key][0]), _f(pwv)])

    rows_d = []
    for site in sorted(daily):
        q = daily[site]
        x2 = pressure_ratio(SITES[site]) ** 2
        glt86 = native.get(site, {}).get("86daily", {})
        for (year, month, day), (tau230, tb230) in sorted(q["230"].items()):
            t345 = q["345"].get((year, month, day), [math.nan, math.nan])
            wind = q["wind"].get((year, month, day), [math.nan])[0]
            if (year, month) == (YEAR, MONTH) and day in glt86:
                (tau86, tb86), src86 = glt86[day], "merra2_am"
            else:
                # derived on loading (tables.py) from the model in derivation_86ghz.json
                tau86 = tb86 = None
                src86 = "derived"
            rows_d.append([site, year, month, day, _f(tau86), _f(tb86), src86, _f(tau230),
                           _f(tb230), _f(t345[0]), _f(t345[1]), _f(wind)])

    DATA.mkdir(exist_ok=True)
    with open(DATA / "merra2_3hourly.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["site", "year", "month", "day", "segment", "tau86", "tb86", "src86",
                    "tau230", "tb230", "tau345", "tb345", "src345", "wind", "pwv"])
        w.writerows(rows3)
    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(["site", "year", "month", "day", "tau86", "tb86", "src86", "tau230", "tb230",
                "tau345", "tb345", "wind"])
    w.writerows(rows_d)
    with open(DATA / DAILY_FILE, "wb") as raw, \
            gzip.GzipFile(filename="", mode="wb", fileobj=raw, compresslevel=9, mtime=0) as fh:
        fh.write(text.getvalue().encode("ascii"))
    old_plain = DATA / "merra2_daily.csv"       # the uncompressed layout of earlier builds
    if old_plain.exists():
        old_plain.unlink()
    derivation = {
        "model": "tau86 = a*(P/P0)^2 + b*tau230; Tb86 = c*Tb230/(1-exp(-tau230))*(1-exp(-tau86)); "
                 "P/P0 = exp(-site elevation / 8000 m)",
        "a": a, "b": b, "c": c,
        "calibration": "every native 86 GHz value of the sources: APEX and KVNYS 3-hourly "
                       "(2018-04-07..13), GLT daily means (weight 8)",
        "n_points": len(pts),
        "checks_against_published_86ghz": validate_86(pts, params),
        "external_86ghz_check": external_check(rows_d, a, b),
        "scaling_345": "tau345(segment) = tau230(segment) * tau345_daily / tau230_daily; "
                       "Tb345 = Tb345_daily/(1-exp(-tau345_daily)) * (1-exp(-tau345))",
    }
    (DATA / "derivation_86ghz.json").write_text(json.dumps(derivation, indent=1) + "\n")
    return derivation


SEARCHED_86GHZ = [
    "IRAM 30m ATM opacity page, http://mainwiki.iram.es/AtmOpacity (ATM2009 tau vs frequency "
    "for pwv 1.5 and 7 mm: figures only, no tabulated 3 mm values)",
    "ARO 12m (Kitt Peak) receiver Tsys tables, aro.as.arizona.edu/12m_docs/Receiver_tsys.htm "
    "(225 GHz tau0 and 88.6 GHz Tsys per scan; no 3 mm opacity, and the receiver temperature "
    "needed to get one from Tsys is not given); ARO equipment summary "
    "(aro.as.arizona.edu/?q=facilities/equipment-summary: typical and best Tsys at 90 and "
    "115 GHz only)",
    "ARO SMT opacity curves, http://aro.as.arizona.edu/smt_docs/opacity_curves.htm (Mt Graham, "
    "not one of our sites; table not in the text reached)",
    "NRAO almatau (Chajnantor ATM dry + wet terms, a model, not a measurement), "
    "http://www.tuc.nrao.edu/~mholdawa/glish/almatau.html (the 86 GHz terms are in the "
    "downloadable script, not in the page text)",
    "KVN: Lee et al. 2011 (arXiv:1110.3881, 22/43 GHz only), KVN status reports "
    "(radio.kasi.re.kr/kvn: sky lines, positions, receiver temperatures, pointing; no opacity), "
    "'100-GHz band test observations of the KVN 21-m radio telescopes' (JKAS 2011, "
    "koreascience.or.kr JAKO201119950684869: abstract only, no opacity), Xu et al. 2024 "
    "(arXiv:2409.07309, 22/43/88/132 GHz geodetic VLBI; no opacity values in the text reached), "
    "L. Petrov's KVN k11352b Tsys page (opacity tables linked, not in the text)",
    "IRAM Newsletters on Pico Veleta / Plateau de Bure conditions (iram.fr/IRAMFR/ARN: the "
    "3 mm time-estimate rules name 4 mm (winter) and 7 mm (summer) pwv, but the matching tau "
    "values are images in the stored HTML; the '30-m telescope manual' Table 4.3 they cite "
    "was not reached)",
    "IRAM Memo 2009-5 (Pety, Bardeau & Reynier, ATM 1985 vs 2009; 115 and 230 GHz opacity vs "
    "pwv as figures only); GILDAS NOEMA sensitivity notes (Tsys tables as figures); NOEMA "
    "introduction (receiver temperatures only)",
    "ALMA: almascience atmosphere-model page and ALMA OT / sensitivity-calculator manuals "
    "(octile PWVs 0.472-5.186 mm, no band-3 opacity in the text); APEX Chajnantor atmosphere "
    "pages (200 GHz and up); submm.eu MOLIERE Chajnantor models (downloadable files only); "
    "Matsushita & Matsuo 2003 (astro-ph/0302016, Pampa la Bola FTS 100-1600 GHz: abstract "
    "only in the text reached)",
    "GLT: cfa.harvard.edu/greenland12m site page, Matsushita et al. 2017 (arXiv:1611.01279, "
    "Summit, 225 GHz), Chen et al. 2023 PASP (arXiv:2307.10468, abstract only); no 86 GHz "
    "opacity at Pituffik in the text reached",
    "VLBA observational status summaries (3 mm SEFDs, no site opacities); MMA memo 118 "
    "(Mauna Kea 225 GHz quartiles); legacy.nrao.edu compare-225 (225 GHz only)",
    "GitHub text index (find_string): 'opacity at 86 GHz', '86 GHz opacity', 'opacity at 3mm', "
    "'opacity at 3 mm', '3 mm opacity', 'opacity at 90 GHz', 'opacity at 100 GHz', "
    "'zenith opacity at 86', 'opacities at 86', 'tau_86', 'tau86', 'almatau': no site value",
]

# A published 3 mm zenith opacity read on 2026-11-24 in the stored page index (the numbers as
# printed; the telescope is not named in the text reached, see ``site_attribution``).
PUBLISHED_3MM = {
    "site": "IRAM",
    "source": "Astronomy & Astrophysics (2004), article aa0177-04, Table 1 'Observational "
              "parameters', https://www.aanda.org/articles/aa/full/2004/41/aa0177-04/table1.html "
              "(only this table page was reached: the article's title, authors, observing dates "
              "and telescope name are not in it)",
    "table_row": {"frequency_GHz": 82.720, "tsys_K": 97, "tau": 0.04, "rho": 0.78,
                  "hpbw_arcsec": 29},
    "table_note": "Tsys is marked as an average system temperature; tau sits beside it and is "
                  "taken to be the zenith opacity averaged over the same observations",
    "site_attribution": "inferred, not stated: the table's beams (29\" at 82.7 GHz down to 9\" "
                        "at 272.8 GHz) follow 2460\"/nu[GHz] within 1\", the beam of a 30 m "
                        "dish, and rho = T_A*/T_mb = 0.78 at 82.7 GHz is the 30m's "
                        "B_eff/F_eff; the IRAM 30m is the only 30 m dish among our sites",
    "conditions": "not given in the text reached: no date, season, PWV or elevation; "
                  "82.7 GHz, not 86 GHz",
    "not_used": {
        "106.355 GHz, tau 0.08": "near the 118.75 GHz oxygen line; the 86 GHz model does not "
                                 "describe it",
        "224.519 GHz, tau 0.29 (same table)": "our model at tau230 = 0.29 gives tau86 = "
                                              "{m29:.3f}, and the published 0.04 is {r29:.2f} of "
                                              "that; not a check: the text does not say the 82.7 "
                                              "and 224.5 GHz averages cover the same hours, and "
                                              "224.5 GHz is not 230 GHz",
    },
}


def external_check(rows_d, a: float, b: float) -> dict:
    """What was found in published sources for a check of the 86 GHz values (see PROVENANCE.md)."""
    apex = sorted(float(r[7]) for r in rows_d if r[0] == "APEX" and r[7] != "")
    years = sorted({int(r[1]) for r in rows_d if r[0] == "APEX"})
    pub = json.loads(json.dumps(PUBLISHED_3MM))
    site = pub["site"]
    x2 = pressure_ratio(SITES[site]) ** 2
    tau230 = np.array([float(r[7]) for r in rows_d if r[0] == site and r[7] != ""])
    ours = tau86_model(x2, tau230, a, b)
    tau_pub = pub["table_row"]["tau"]
    lo, hi = (float(np.percentile(ours, q)) for q in (5, 95))
    m29 = tau86_model(x2, 0.29, a, b)
    key = "224.519 GHz, tau 0.29 (same table)"
    pub["not_used"][key] = pub["not_used"][key].format(m29=m29, r29=tau_pub / m29)
    pub["ours"] = {
        "what": "derived tau86 of the extract's IRAM daily means, all 12 months, 2009-2018 "
                "(tau86 = a (P/P0)^2 + b tau230, as loaded by hitops.weather.tables)",
        "n_days": int(ours.size),
        "percentiles_5_16_50_84_95": [round(float(np.percentile(ours, q)), 4)
                                      for q in (5, 16, 50, 84, 95)],
        "dry_term": round(float(a * x2), 4),
        "percentile_of_published_tau": round(100.0 * float(np.mean(ours < tau_pub)), 1),
        "published_over_our_median": round(tau_pub / float(np.median(ours)), 3),
    }
    pub["tolerance"] = ("the published tau must lie inside our 5-95 percentile range of IRAM daily "
                        "means: with no date, season or PWV stated, only this climatological "
                        "consistency can be tested, not an agreement to a stated precision")
    pub["within_tolerance"] = bool(lo <= tau_pub <= hi)
    return {
        "published_3mm_figure_sites": [site],
        "two_site_requirement_met": False,
        "statement": "Published 3 mm zenith opacity numbers were found for one of the 8 sites "
                     "only (IRAM, and there the telescope is inferred from the table's beam sizes, "
                     "not named), with no stated date, season or PWV; for the other sites no "
                     "published 86 GHz (3 mm) zenith opacity with numbers could be reached from "
                     "this machine (no network; stored page, documentation, issue and code "
                     "indexes searched on 2026-11-24, listed in 'searched'). The IRAM figure is "
                     "checked only for climatological consistency (published_points); the other "
                     "86 GHz check is against the database's own native 86 GHz values "
                     "(checks_against_published_86ghz, leave-one-site-out).",
        "published_points": [pub],
        "searched": SEARCHED_86GHZ,
        "context_225ghz": {
            "source": "NRAO ALMA site studies, 'Comparison of zenith optical depth', "
                      "https://legacy.nrao.edu/alma/site/compare-225 (S. Radford, 2003-12-17): "
                      "Chajnantor 225 GHz tipper, 1995-04..2003-10, 85% uptime",
            "published_tau225_quartiles_chajnantor": [0.037, 0.061, 0.122],
            "extract_tau230_quartiles_apex_all_months": [round(float(np.percentile(apex, q)), 4)
                                                          for q in (25, 50, 75)],
            "extract_years": [years[0], years[-1]],
            "extract_over_published_median": round(float(np.percentile(apex, 50)) / 0.061, 3),
            "note": "a 225/230 GHz comparison, not an 86 GHz one: different years (1995-2003 vs "
                    "2009-2018), 225 vs 230 GHz, a measured tipper on the plateau vs MERRA-2 + am "
                    "at the APEX grid point; no tolerance is claimed",
        },
    }


def main():
    derivation = build()
    print(f"wrote {DATA}: a={derivation['a']:.4f} b={derivation['b']:.4f} c={derivation['c']:.4f}")
    for site, res in derivation["checks_against_published_86ghz"].items():
        print(site, res)


if __name__ == "__main__":
    main()
