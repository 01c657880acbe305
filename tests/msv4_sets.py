"""Processing sets for the MSv4 tests: Measurement Sets v2 converted by xradio itself.

``convert`` runs xradio's ``convert_msv2_to_processing_set`` (its default arcae
backend, as a user runs it).  ``simulator_layout`` lays a set out with
casatools.simulator (tests/solutions_scene.py: two target windows of 16 channels,
two fields over three scans) and writes random DATA and a flag pattern into it
with python-casacore, so every value the readers return has a truth to meet.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
from pathlib import Path
from typing import Dict, List, Sequence

import numpy as np

from solutions_scene import TARGET_CENTRES_HZ, lay_out

#: the pair the MSv4 tests convert: noisy, two scans, rows stored baseline by baseline
SCANS = (("M87", 0.0, 20.0), ("3C273", 20.0, 40.0), ("M87", 40.0, 60.0))


def convert(ms: Path, out: Path) -> Path:
    """The processing set xradio writes for ``ms`` (its name must end in .ps.zarr)."""
    from xradio.measurement_set import convert_msv2_to_processing_set

    logging.getLogger("toolviper").setLevel(logging.WARNING)
    convert_msv2_to_processing_set(str(ms), str(out))
    return out


def simulator_layout(ms: Path, seed: int = 5) -> Path:
    """A casatools.simulator layout with random DATA and about 10% of FLAG set."""
    from casacore import tables as pt

    lay_out(ms, TARGET_CENTRES_HZ, SCANS, "2017/04/05/02:00:00", ["PV", "PB", "AP", "GL"])
    rng = np.random.default_rng(seed)
    with pt.table(str(ms), readonly=False, ack=False) as t:
        shape = t.getcol("DATA").shape
        t.putcol("DATA", (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64))
        t.putcol("FLAG", rng.random(shape) < 0.1)
    return ms


def file_digests(root: Path, skip=()) -> Dict[str, str]:
    """{relative path: sha256} of every file under ``root`` outside the ``skip`` names."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        rel = path.relative_to(root)
        if path.is_file() and not any(part in skip for part in rel.parts):
            out[str(rel)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def copies_of(paths: Sequence, directory: Path) -> List[str]:
    """Private copies of sets or stores in ``directory``, under their own names."""
    out = []
    for path in paths:
        shutil.copytree(path, Path(directory) / Path(path).name)
        out.append(str(Path(directory) / Path(path).name))
    return out
