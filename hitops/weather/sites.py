"""Sites of the ngEHT weather tables and the station codes that map onto them.

Folder names, codes, positions and elevations are those of the ngEHT site
table (``legacy/Telescope_Site_Matrix.csv`` of Smithsonian/ngehtsim-weather-builder).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional


@dataclass(frozen=True)
class Site:
    folder: str          # folder name in Smithsonian/ngeht-weather weather_data/
    code: str            # two-letter station code
    name: str
    latitude: float      # deg
    longitude: float     # deg
    elevation_m: float


SITES: Dict[str, Site] = {s.folder: s for s in [
    Site("ALMA", "AA", "ALMA, Chajnantor, Chile", -23.03217, -67.75536, 5043),
    Site("APEX", "AP", "APEX 12 m, Chajnantor, Chile", -23.00572, -67.75928, 5061),
    Site("GLT", "GL", "Greenland Telescope, Pituffik, Greenland", 76.535087, -68.685908, 67),
    Site("IRAM", "PV", "IRAM 30 m, Pico Veleta, Spain", 37.066145, -3.392597, 2864),
    Site("JCMT", "JC", "JCMT, Maunakea, Hawaii", 19.82293, -155.47709, 4074),
    Site("KP", "KP", "ARO 12 m, Kitt Peak, Arizona", 31.953279, -111.614806, 1927),
    Site("KVNPC", "KC", "KVN Pyeongchang, Korea", 37.534119, 128.449676, 504),
    Site("KVNYS", "KY", "KVN Yonsei, Seoul, Korea", 37.565159, 126.941027, 92),
    Site("LMT", "LM", "LMT 50 m, Sierra Negra, Mexico", 18.98575, -97.31481, 4618),
    Site("NOEMA", "PB", "NOEMA, Plateau de Bure, France", 44.63366, 5.90669, 2554),
    Site("SMA", "SM", "SMA, Maunakea, Hawaii", 19.8241, -155.47823, 4075),
    Site("SMT", "AZ", "SMT 10 m, Mt Graham, Arizona", 32.7016, -109.8913, 3173),
    Site("SPT", "SP", "South Pole Telescope", -90.0, 45.0, 2820),
]}

#: station code -> site folder
CODE_TO_FOLDER: Dict[str, str] = {s.code: s.folder for s in SITES.values()}

#: sites without tables of their own and the site whose tables stand in for them
PROXIES: Dict[str, str] = {
    # KVN Pyeongchang has no folder in the public text tables (only in ngehtsim's
    # binary files); KVN Yonsei is the nearest site with tables (~130 km west,
    # 412 m lower, so its opacities are if anything pessimistic for Pyeongchang).
    "KVNPC": "KVNYS",
}


def distance_km(a: Site, b: Site) -> float:
    """Great-circle distance between two sites (km, spherical Earth)."""
    p1, p2 = math.radians(a.latitude), math.radians(b.latitude)
    dl = math.radians(b.longitude - a.longitude)
    c = math.sin(p1) * math.sin(p2) + math.cos(p1) * math.cos(p2) * math.cos(dl)
    return 6371.0 * math.acos(max(-1.0, min(1.0, c)))


def resolve(name: str) -> Optional[Site]:
    """The site named by a folder name or a station code (case-insensitive), or None."""
    key = str(name).strip()
    for folder, site in SITES.items():
        if key.upper() in (folder.upper(), site.code.upper()):
            return site
    return None


def pressure_ratio(site: Site, scale_height_m: float = 8000.0) -> float:
    """Surface pressure over sea-level pressure, exp(-h / H) (isothermal atmosphere)."""
    return math.exp(-site.elevation_m / scale_height_m)
