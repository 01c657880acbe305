"""Write a table (a directory) under a temporary name and move it into place when whole.

A writer that fails or is interrupted leaves nothing that looks like a result: the
temporary sibling is removed, and an existing table of the same name is replaced
only once the new one is complete.
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def replaced_directory(path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write into; it becomes ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        yield partial
        if path.exists():
            shutil.rmtree(path)
        partial.rename(path)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
