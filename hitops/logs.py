"""Readable logging and progress for long work.

One format everywhere (time, level, message); progress of long loops is
reported at most every few seconds through :class:`Progress`, so logs stay
short when captured by Stimela or a batch system.
"""

from __future__ import annotations

import logging
import sys
import time

_FORMAT = "%(asctime)s %(levelname)-7s %(message)s"


def setup_logging(level: int = logging.INFO) -> logging.Logger:
    logger = logging.getLogger("hitops")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(_FORMAT, datefmt="%H:%M:%S"))
        logger.addHandler(handler)
        logger.propagate = False
    logger.setLevel(level)
    return logger


class Progress:
    """Log ``label: done/total (pct)`` at most once every ``every`` seconds."""

    def __init__(self, label: str, total: int, every: float = 5.0,
                 logger: logging.Logger | None = None):
        self.label, self.total, self.every = label, max(int(total), 1), every
        self.log = logger or logging.getLogger("hitops")
        self.start = self.last = time.perf_counter()
        self.done = 0

    def update(self, n: int = 1) -> None:
        self.done += n
        now = time.perf_counter()
        if now - self.last >= self.every or self.done >= self.total:
            self.last = now
            self.log.info("%s: %d/%d (%.0f%%, %.1f s)", self.label, self.done, self.total,
                          100.0 * self.done / self.total, now - self.start)
