"""Shared helpers for benchmarks: whole-process timing and docs/performance.md sections.

Each benchmark owns one section of docs/performance.md, delimited by
``<!-- bench:KEY -->`` and ``<!-- /bench:KEY -->``; rerunning it replaces
only that section, so benchmarks can be run one at a time.
"""

from __future__ import annotations

import os
import platform
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PERF_DOC = ROOT / "docs" / "performance.md"
PLOT_DIR = ROOT / "docs" / "figures"


def machine_line() -> str:
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}")


def run_process(cmd, env=None, cwd=None) -> dict:
    """Run a command as its own process; return wall, CPU time and peak RSS.

    Peak RSS comes from the kernel's accounting of the child (ru_maxrss of
    RUSAGE_CHILDREN after wait4), in MB.
    """
    full_env = dict(os.environ, **(env or {}))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=full_env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    output = proc.stdout.read()
    proc.stdout.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed:\n{output}")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_mb": usage.ru_maxrss / 1024.0, "output": output}


def replace_section(key: str, markdown: str, doc: Path = PERF_DOC) -> None:
    """Put ``markdown`` between this benchmark's markers in ``doc``."""
    doc.parent.mkdir(parents=True, exist_ok=True)
    text = doc.read_text() if doc.exists() else "# Performance\n\n"
    start, end = f"<!-- bench:{key} -->", f"<!-- /bench:{key} -->"
    block = f"{start}\n{markdown.strip()}\n{end}"
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    doc.write_text(text)


def median(values):
    values = sorted(values)
    n = len(values)
    return values[n // 2] if n % 2 else 0.5 * (values[n // 2 - 1] + values[n // 2])


if __name__ == "__main__":  # pragma: no cover
    print(machine_line(), file=sys.stderr)
