"""``hitops simulate --format msv4``: each band's Measurement Set converted once by xradio.

The scene is written as Measurement Sets v2 first (CASA tasks and WSClean read only
those, docs/msv4.md "Between the two worlds"), then each is converted with xradio's
``convert_msv2_to_processing_set`` into ``<prefix>-<band>.ps.zarr`` beside it.  Chosen
on purpose:

* ``partition_scheme=["FIELD_ID"]``: one partition per (window, field), so a phase-
  referencing scene's target and calibrator are partitions of their own, each with its
  one phase centre in its ``field_and_source`` (xradio's default [] puts alternating
  scans of both fields in one partition, which hitops reads too);
* ``main_chunksize={"time": n}`` with n time steps of about 10^5 rows: xradio's default
  (about 128 MiB of the largest variable per chunk) puts a 10^6-row partition in one
  chunk, and hitops's chunked read then decompresses it whole for every chunk
  (docs/msv4.md, "Measured": 0.14 s against 0.06 s with 10^5-row chunks).

Never half-written: each store is converted under a hidden name (xradio names the
partitions after the Measurement Set, not the store, so the partitions are named as a
user's own conversion names them) and renamed only when every band's conversion has
finished; a failure removes the hidden stores and leaves no ``.ps.zarr``.
"""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path
from typing import Dict, Iterable

from ..errors import SceneError

log = logging.getLogger("hitops.simulate")

#: the rows of one time chunk of the stores written (docs/msv4.md measured 10^5)
ROWS_PER_CHUNK = 100_000

#: the values of --format
FORMATS = ("ms", "msv4")


def check_format(output_format: str) -> None:
    """Refuse an unknown --format, or msv4 without xradio, before anything is simulated."""
    if output_format not in FORMATS:
        raise SceneError(f"--format {output_format!r} is not one of {', '.join(FORMATS)}: "
                          "'ms' writes Measurement Sets v2, 'msv4' also MSv4 processing sets")
    if output_format == "msv4":
        try:
            import xradio.measurement_set  # noqa: F401
        except ImportError as exc:
            raise SceneError(f"--format msv4 needs xradio ({exc}); install the msv4 extra: "
                              "pip install 'hitops[msv4]'") from None


def store_path(ms: Path) -> Path:
    """``<dir>/<prefix>-<band>.ps.zarr`` for ``<dir>/<prefix>-<band>.ms``."""
    return ms.with_name(ms.name[:-len(".ms")] + ".ps.zarr")


def time_chunk(n_station: int) -> int:
    """Time steps per chunk: about ``ROWS_PER_CHUNK`` rows of the full baseline grid."""
    n_baseline = max(1, n_station * (n_station - 1) // 2)
    return max(1, math.ceil(ROWS_PER_CHUNK / n_baseline))


def convert_bands(ms_paths: Iterable[Path], n_station: int) -> Dict[Path, Path]:
    """Convert each Measurement Set into its store; {ms path: store path}, all or none."""
    from xradio.measurement_set import convert_msv2_to_processing_set

    # hitops writes no SOURCE table, and xradio warns of that once per partition
    logging.getLogger("toolviper").setLevel(logging.ERROR)
    chunk = {"time": time_chunk(n_station)}
    staged: Dict[Path, Path] = {}
    try:
        for ms in ms_paths:
            final = store_path(ms)
            hidden = final.with_name(f".{final.name[:-len('.ps.zarr')]}.writing.ps.zarr")
            _remove(hidden)
            staged[ms] = hidden
            convert_msv2_to_processing_set(str(ms), str(hidden), partition_scheme=["FIELD_ID"],
                                           main_chunksize=chunk)
        out = {}
        for ms, hidden in staged.items():
            final = store_path(ms)
            _remove(final)
            hidden.rename(final)
            out[ms] = final
    except BaseException:
        for hidden in staged.values():
            _remove(hidden)
        raise
    log.info("simulate: converted %d band(s) to MSv4 processing sets (time chunks of %d)",
             len(out), chunk["time"])
    return out


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
