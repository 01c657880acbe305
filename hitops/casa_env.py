"""CASA's offline data configuration, set up without touching ~/.casa.

casatools refuses to import offline (AutoUpdatesNotAllowed) unless its
configuration points ``measurespath`` at local data and turns the automatic
updates off.  We write a site configuration file that points at the data of
the pip package ``casadata`` and name it in ``CASASITECONFIG`` before the first
``import casatools``.  Debian's /usr/share/casacore/data is refused by
casatools 6.7 ("measures data is not available"), so casadata is required.

Call :func:`ensure_casa_offline` before importing casatools or casatasks, or
run ``python -m hitops.casa_env`` to write the file and print its path.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import ExternalToolError

_TEMPLATE = """# written by hitops.casa_env: CASA offline data configuration
measurespath = {path!r}
measures_auto_update = False
data_auto_update = False
# CASA would otherwise drop casa-<date>.log into whatever directory a step runs in;
# hitops.casa.runner reads SEVERE lines back from this same per-process file
import os as _os, tempfile as _tempfile
logfile = _os.path.join(_tempfile.gettempdir(), "hitops-casa-%d.log" % _os.getpid())
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
    """Where the site configuration lives: $HITOPS_CASA_CONFIG or a user cache file."""
    explicit = os.environ.get("HITOPS_CASA_CONFIG")
    if explicit:
        return Path(explicit)
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return cache / "hitops" / "casasiteconfig.py"


def ensure_casa_offline() -> Path:
    """Write (if needed) and select the offline configuration; return its path.

    A ``CASASITECONFIG`` already set by the user is respected.
    """
    if os.environ.get("CASASITECONFIG"):
        return Path(os.environ["CASASITECONFIG"])
    path = config_file()
    text = _TEMPLATE.format(path=str(casadata_path()))
    if not path.exists() or path.read_text() != text:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    os.environ["CASASITECONFIG"] = str(path)
    return path


if __name__ == "__main__":
    print(ensure_casa_offline())
