"""The ``hitops`` command: one subcommand per tool schema.

Each subcommand's options come from ``hitops/schemas/<tool>.yml``; its
implementation is the function ``run`` of module ``hitops.<tool>.app``,
imported only when that subcommand runs so ``hitops --help`` stays fast.
Bad input (any :class:`hitops.errors.HitopsError`) ends with a one-paragraph
message and exit status 2, never a traceback.
"""

from __future__ import annotations

import importlib
import logging
import sys

import click

from . import __version__
from .errors import HitopsError
from .logs import setup_logging
from .schema import clickify, tools
from .startup import fast_exit, lean_start

log = logging.getLogger("hitops")


#: tools whose work runs in numba kernels (their start-up initialises numba's CPU target)
NUMBA_TOOLS = {"calibrate", "diagnose", "simulate"}


def _make_command(tool: str) -> click.Command:
    def invoke(**params):
        setup_logging()
        # the stack without SciPy's optional hooks: ~0.3 s less start-up (hitops/startup.py)
        lean_start(numba_target=tool in NUMBA_TOOLS)
        module = importlib.import_module(f"hitops.{tool}.app")
        try:
            module.run(**params)
        except HitopsError as err:
            log.error("%s", err)
            sys.exit(err.exit_code)
        if tool in NUMBA_TOOLS:
            # numba's interpreter teardown alone takes 0.3-0.4 s (hitops/startup.py)
            fast_exit(0)

    return clickify(tool, invoke)


@click.group()
@click.version_option(__version__, prog_name="hitops")
def cli():
    """HITOPS: frequency phase transfer for mm-VLBI at arbitrary frequency ratios."""


for _tool in tools():
    cli.add_command(_make_command(_tool))


def main():
    cli()


if __name__ == "__main__":
    main()
