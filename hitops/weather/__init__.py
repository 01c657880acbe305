"""MERRA-2 site weather from the public ngEHT tables, shipped as a compact extract.

:func:`station_weather` gives zenith opacity and sky brightness temperature per
band (86 GHz derived where not native) and wind speed for a station on a time
grid; ``hitops/weather/data/PROVENANCE.md`` says where every number comes from
and ``python -m hitops.weather.build_extract`` rebuilds the extract from the
verbatim source rows in ``hitops/weather/sources/``.
"""

from .tables import (STATISTICS, StationWeather, WeatherError, effective_temperature,
                     months_with_data, sites_with_tables, station_weather)

__all__ = ["station_weather", "StationWeather", "WeatherError", "effective_temperature",
           "sites_with_tables", "months_with_data", "STATISTICS"]
