"""FPT forecast per site and month from MERRA-2 weather: ``hitops forecast`` and :func:`forecast`."""

from .api import forecast

__all__ = ["forecast"]
