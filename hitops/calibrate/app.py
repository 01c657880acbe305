"""Entry point of ``hitops calibrate`` (parameters from hitops/schemas/calibrate.yml)."""

from __future__ import annotations


def run(**params):
    from .api import calibrate

    calibrate(**params)
