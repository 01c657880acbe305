"""Entry point of ``hitops forecast`` (parameters and defaults from hitops/schemas/forecast.yml)."""

from .api import forecast as run  # noqa: F401
