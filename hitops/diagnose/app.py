"""CLI entry of ``hitops diagnose`` (parameters from hitops/schemas/diagnose.yml)."""

from __future__ import annotations

from .api import diagnose


def run(**params) -> dict:
    return diagnose(**params)
