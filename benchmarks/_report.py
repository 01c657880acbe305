"""Shared helpers for benchmarks: whole-process timing and docs/performance.md sections.

Each benchmark owns one section of docs/performance.md, delimited by
``<!-- bench:KEY -->`` and ``<!-- /bench:KEY -->``; rerunning it replaces
only that section, so benchmarks can be run one at a time.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PERF_DOC = ROOT / "docs" / "performance.md"
PLOT_DIR = ROOT / "docs" / "figures"


def machine_line() -> str:
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}")


def load_line() -> str:
    """The load average when a table is written: whether the runs had the machine to
    themselves (a shared machine's other jobs show here, not in the runs' own figures)."""
    one, five, _ = os.getloadavg()
    return f"load average {one:.1f} (1 min) and {five:.1f} (5 min) when written"


# A minimal launcher process between the benchmark and the measured command.  Linux
# records the pre-exec address space's high-water RSS in the exec'd process's maxrss
# (a vfork/fork child execs from the parent's memory image), so measuring a child of
# a benchmark process that has itself used gigabytes (e.g. building a 10^7-row pair)
# would report the benchmark's peak, not the command's.  The launcher is a small
# ``python -S`` process, so the measured command's ru_maxrss is its own (the
# launcher's ~10 MB image is the floor).  It also times the command without its own
# start-up and reads the output while waiting (no pipe-buffer deadlock).
_LAUNCHER = r"""
import json, os, sys, time
out, cmd = sys.argv[1], sys.argv[2:]
t0 = time.perf_counter()
pid = os.posix_spawnp(cmd[0], cmd, os.environ)
_, status, usage = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(out, "w") as f:
    json.dump({"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
               "maxrss_kb": usage.ru_maxrss}, f)
code = os.waitstatus_to_exitcode(status)
sys.exit(code if code >= 0 else 128 - code)
"""


def run_process(cmd, env=None, cwd=None) -> dict:
    """Run a command as its own process; return wall, CPU time and peak RSS.

    Peak RSS comes from the kernel's accounting of the command's process
    (ru_maxrss from wait4 in a small launcher process, see ``_LAUNCHER``), in MB.
    """
    import json
    import tempfile

    full_env = dict(os.environ, **(env or {}))
    fd, stats_path = tempfile.mkstemp(prefix="run-process-", suffix=".json")
    os.close(fd)
    try:
        proc = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER, stats_path,
                                 *map(str, cmd)], env=full_env, cwd=cwd,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        output, _ = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(map(str, cmd))} failed:\n{output}")
        with open(stats_path) as f:
            stats = json.load(f)
    finally:
        os.unlink(stats_path)
    return {"wall_s": stats["wall_s"], "cpu_s": stats["cpu_s"],
            "peak_rss_mb": stats["maxrss_kb"] / 1024.0, "output": output}


def replace_section(key: str, markdown: str, doc: Path = PERF_DOC) -> None:
    """Put ``markdown`` between this benchmark's markers in ``doc``."""
    doc.parent.mkdir(parents=True, exist_ok=True)
    text = doc.read_text() if doc.exists() else "# Performance\n\n"
    start, end = f"<!-- bench:{key} -->", f"<!-- /bench:{key} -->"
    block = f"{start}\n{markdown.strip()}\n{end}"
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    doc.write_text(text)


def save_figure(fig, path: Path) -> Path:
    """Lay out, write (creating the folder) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def median(values):
    values = sorted(values)
    n = len(values)
    return values[n // 2] if n % 2 else 0.5 * (values[n // 2 - 1] + values[n // 2])


if __name__ == "__main__":  # pragma: no cover
    print(machine_line(), file=sys.stderr)
