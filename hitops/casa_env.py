"""CASA's offline data configuration, set up without touching ~/.casa.

casatools refuses to import offline (AutoUpdatesNotAllowed) unless its
configuration points ``measurespath`` at local data and turns the automatic
updates off.  We write a site configuration file that points at the data of
the pip package ``casadata`` and name it in ``CASASITECONFIG`` before the first
``import casatools``.  Debian's /usr/share/casacore/data is refused by
casatools 6.7 ("measures data is not available"), so casadata is required.

The file lives inside the Python environment (``<sys.prefix>/etc/hitops/``),
next to the casadata it names: a per-user file was shared by every clone, so a
second clone silently rewrote it and deleting that clone broke CASA for the
first (issue 17).

Call :func:`ensure_casa_offline` before importing casatools or casatasks, or
run ``python -m hitops.casa_env`` to write the file and print its path.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .errors import ExternalToolError

_TEMPLATE = """# written by hitops.casa_env: CASA offline data configuration
measurespath = {path!r}
measures_auto_update = False
data_auto_update = False
# CASA would otherwise drop casa-<date>.log into whatever directory a step runs in.
# Until hitops.casa.runner names the log of a task (HITOPS_CASA_LOG, or casa.log
# beside the task's output), CASA's start-up lines go nowhere: no file in the
# working directory or in /tmp
import os as _os
logfile = _os.environ.get("HITOPS_CASA_LOG") or _os.devnull
"""


def casadata_path() -> Path:
    """The ``__data__`` directory of the pip package casadata."""
    try:
        import casadata
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ExternalToolError(
            "CASA's data package 'casadata' is not installed; run 'make setup' or "
            "'pip install casadata'") from err
    path = Path(casadata.__file__).parent / "__data__"
    if not (path / "geodetic").is_dir():
        raise ExternalToolError(f"casadata at {path} has no geodetic/ directory; "
                                "reinstall it with 'pip install --force-reinstall casadata'")
    return path


def config_file() -> Path:
    """Where the site configuration lives: $HITOPS_CASA_CONFIG, else inside the environment.

    ``<sys.prefix>/etc/hitops/casasiteconfig.py``: each environment has its own
    casadata, so each gets its own file (see the module docstring).
    """
    explicit = os.environ.get("HITOPS_CASA_CONFIG")
    if explicit:
        return Path(explicit)
    return Path(sys.prefix) / "etc" / "hitops" / "casasiteconfig.py"


def ensure_casa_offline() -> Path:
    """Write (if needed) and select the offline configuration; return its path.

    A ``CASASITECONFIG`` already set by the user is respected.
    """
    if os.environ.get("CASASITECONFIG"):
        return Path(os.environ["CASASITECONFIG"])
    path = config_file()
    text = _TEMPLATE.format(path=str(casadata_path()))
    if not path.exists() or path.read_text() != text:
        # a per-process temporary name: two processes writing at once (parallel
        # tests, dask workers) must not replace each other's half-written file
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(text)
            tmp.replace(path)
        except OSError as err:
            # e.g. an environment installed by another user (read-only sys.prefix)
            raise ExternalToolError(
                f"cannot write CASA's offline data configuration {path} ({err.strerror}); "
                "run 'python -m hitops.casa_env' once as the environment's owner, "
                "or set HITOPS_CASA_CONFIG to a writable file") from err
    os.environ["CASASITECONFIG"] = str(path)
    return path


if __name__ == "__main__":
    from .errors import HitopsError

    try:
        print(ensure_casa_offline())
    except HitopsError as err:  # one line, as the CLI prints it (scripts/setup.sh relies on it)
        sys.exit(f"hitops: {err}")
