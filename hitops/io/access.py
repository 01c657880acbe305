"""Access to a Measurement Set before any work is done on it: can it be written, is there
room, who else has it open, and where is it damaged.

Each check turns an operating-system or casacore condition into one
:class:`hitops.errors.HitopsError` line that names the table and the remedy,
instead of a casacore traceback in the middle of a run (or a silent wait):

* :func:`require_writable`: read-only file systems and permissions;
* :func:`require_free_space`: new columns that would not fit (a write that runs
  out of space can abort the process inside casacore);
* :class:`RunLock`: two hitops runs on one set (an ``flock`` on the set's
  directory: the second waits, then gives up after a bounded time);
* :func:`wait_for_table_lock`: another process (a notebook, casabrowser) holding
  casacore's own table lock; the wait is announced, names the process where
  Linux's /proc tells it, and is bounded;
* :func:`locate_damage`: after an unexpected casacore error, which table and column
  cannot be read, so the message can name them.

An MSv4 processing set (a zarr store, hitops/io/msv4/) has no subtables, no casacore
locks and no casacore damage to locate: those checks return at once for one (its
structure is checked whole by :func:`hitops.io.msv4.store.open_store`); write access is
a probe file in each partition, the run lock and the free space are the same.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Iterable, List, Optional

from ..errors import MeasurementSetError
from . import tables
from .msv4.store import is_processing_set

log = logging.getLogger("hitops")

#: subtables every reader here needs
REQUIRED_SUBTABLES = ("ANTENNA", "DATA_DESCRIPTION", "FIELD", "POLARIZATION", "SPECTRAL_WINDOW")


def require_subtables(ms: str, role: str, names: Iterable[str] = REQUIRED_SUBTABLES) -> None:
    """Raise naming the first subtable that is missing (a copy that lost a directory)."""
    if is_processing_set(ms):   # no subtables: open_store has checked its partitions
        return
    for name in names:
        if not (Path(ms) / name / "table.dat").is_file():
            raise MeasurementSetError(
                f"{role} '{ms}' has no {name} subtable ({Path(ms) / name} is missing or not a "
                "table); the set is incomplete: copy it again from its source or re-import it")


def require_writable(ms: str, role: str) -> None:
    """Raise unless ``ms`` can be opened for writing (read-only mount, permissions)."""
    if is_processing_set(ms):
        return _require_writable_store(ms, role)
    problem = None
    for path in [Path(ms), *sorted(Path(ms).glob("table.*"))]:
        if not os.access(path, os.W_OK):
            problem = f"{path} is not writable by this user"
            break
    if problem is None:
        try:
            with tables.main_table(ms, writable=True, user_locks=True):
                pass
        except RuntimeError as err:
            problem = " ".join(str(err).split())
    if problem is None:
        # root passes os.access on a read-only mount; statvfs knows better
        if os.statvfs(ms).f_flag & os.ST_RDONLY:
            problem = "it is on a read-only file system"
    if problem:
        raise MeasurementSetError(
            f"{role} '{ms}' cannot be written ({problem}); hitops adds its output columns "
            "there: copy the set to a writable place (cp -r) and run on the copy")


def _require_writable_store(ps: str, role: str) -> None:
    """A processing set's partitions take new arrays: a probe file in each (a probe, not
    os.access, so a read-only file system is seen, for root too)."""
    import tempfile

    for part in sorted(p for p in Path(ps).iterdir() if (p / "zarr.json").is_file()):
        try:
            tempfile.TemporaryFile(dir=part).close()
        except OSError as err:
            raise MeasurementSetError(
                f"{role} '{ps}' cannot be written ({part.name}: {err.strerror}); hitops adds "
                "its output data groups there: copy the store to a writable place (cp -r) "
                "and run on the copy") from None


def require_free_space(ms: str, n_bytes: int, what: str) -> None:
    """Raise if the file system of ``ms`` has less than ``n_bytes`` (plus 5%) free."""
    need = int(n_bytes * 1.05) + (1 << 20)
    free = shutil.disk_usage(ms).free
    if free < need:
        raise MeasurementSetError(
            f"not enough space for {what} in '{ms}': about {need / 1e6:.1f} MB needed, "
            f"{free / 1e6:.1f} MB free on its file system ({(need - free) / 1e6:.1f} MB "
            "missing); free some space or copy both sets to a larger disk")


def holders(ms: str) -> List[str]:
    """'pid N (command)' of other processes with files of ``ms`` open (Linux /proc; best effort)."""
    root = os.path.realpath(ms) + os.sep
    found = []
    me = os.getpid()
    for entry in os.scandir("/proc") if os.path.isdir("/proc") else []:
        if not entry.name.isdigit() or int(entry.name) == me:
            continue
        try:
            fds = os.listdir(f"/proc/{entry.name}/fd")
            for fd in fds:
                target = os.readlink(f"/proc/{entry.name}/fd/{fd}")
                if target.startswith(root):
                    with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                        cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
                    found.append(f"pid {entry.name} ({cmd[:80]})")
                    break
        except OSError:   # a process that ended, or one we may not inspect
            continue
    return found


class RunLock:
    """Exclusive lock of one Measurement Set against other hitops runs, for a whole run.

    An ``flock`` on the set's directory: nothing is written into the set, the lock
    ends with the process (even on SIGKILL), and a second run waits for the first,
    saying so, for at most ``timeout_s`` seconds.
    """

    def __init__(self, ms: str, timeout_s: float, role: str = "Measurement Set"):
        self.ms, self.timeout_s, self.role = ms, float(timeout_s), role
        self.fd: Optional[int] = None

    def __enter__(self) -> "RunLock":
        self.fd = os.open(self.ms, os.O_RDONLY)
        deadline = time.monotonic() + self.timeout_s
        announced = False
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                if announced:
                    log.info("the other hitops run on %s has finished; going on", self.ms)
                return self
            except OSError as err:
                if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise
            if time.monotonic() >= deadline:
                os.close(self.fd)
                self.fd = None
                who = holders(self.ms)
                raise MeasurementSetError(
                    f"{self.role} '{self.ms}' is being written by another hitops run"
                    + (f" ({', '.join(who)})" if who else "")
                    + f"; waited {self.timeout_s:.0f} s: let it finish and run again, or "
                    "raise --lock-timeout")
            if not announced:
                log.warning("%s is being written by another hitops run; waiting up to %.0f s "
                            "for it to finish", self.ms, self.timeout_s)
                announced = True
            time.sleep(0.2)

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.close(self.fd)   # releases the flock
            self.fd = None


def wait_for_table_lock(ms: str, write: bool, timeout_s: float, role: str) -> None:
    """Wait (announced, bounded) until casacore's lock of ``ms`` can be taken, then release it.

    An idle process that opened the table with casacore's default auto-locking
    (a notebook, casabrowser) keeps its lock until it touches the table again,
    and a writer then waits forever without a word; here the wait is said and
    ends after ``timeout_s`` with one line naming the holder.
    """
    if is_processing_set(ms):   # zarr has no table locks (the run lock still holds)
        return
    deadline = time.monotonic() + float(timeout_s)
    announced = False
    with tables.main_table(ms, writable=write, user_locks=True) as t:
        while True:
            t.lock(write=write, nattempts=1)
            if t.haslock(write):
                t.unlock()
                if announced:
                    log.info("%s is free now; going on", ms)
                return
            who = holders(ms)
            if time.monotonic() >= deadline:
                raise MeasurementSetError(
                    f"{role} '{ms}' is locked by another process"
                    + (f" ({', '.join(who)})" if who else "")
                    + f"; waited {float(timeout_s):.0f} s for its "
                    f"{'lock' if write else 'write lock'} to clear: close the table there "
                    "(e.g. table.close() in a notebook, or quit casabrowser/CASA) and run "
                    "again, or raise --lock-timeout")
            if not announced:
                log.warning("%s is locked by another process%s; waiting up to %.0f s for it "
                            "to release the table", ms, f" ({', '.join(who)})" if who else "",
                            float(timeout_s))
                announced = True
            time.sleep(1.0)


def raise_if_damaged(err: Exception, read) -> None:
    """Turn an unexpected casacore error into one naming the damaged table and column.

    ``read``: (ms, columns) pairs that were being read (columns None: every column,
    as for a calibration table, whose remedy is to rerun the step that wrote it).
    Returns without raising when every column reads (the error had another cause, and
    is re-raised by the caller).
    """
    for ms, columns in read:
        damage = locate_damage(ms, None if columns is None else list(dict.fromkeys(columns)))
        if damage:
            remedy = ("restore the set from its source or a backup" if columns is not None
                      else "rerun the task that wrote the table")
            raise MeasurementSetError(f"'{ms}' is damaged: {damage}; nothing was changed: "
                                      f"{remedy}") from err


def locate_damage(ms: str, columns: Optional[Iterable[str]],
                  step: int = 200_000) -> Optional[str]:
    """'column C, rows a-b: message' for the first column of ``ms`` that cannot be read.

    Reads each column in blocks with python-casacore; used only after an
    unexpected error, to name what is damaged.  None when everything reads (and for a
    processing set, which python-casacore does not read).
    """
    if is_processing_set(ms):
        return None
    try:
        t = tables.main_table(ms)
    except RuntimeError as err:
        return f"the table itself: {' '.join(str(err).split())}"
    with t:
        n_row = t.nrows()
        for column in (t.colnames() if columns is None else columns):
            if column not in t.colnames():
                continue
            for start in range(0, max(n_row, 1), step):
                n = min(step, n_row - start)
                try:
                    if n > 0:
                        t.getcol(column, start, n)
                except RuntimeError as err:
                    return (f"column {column}, rows {start}-{start + n - 1}: "
                            f"{' '.join(str(err).split())}")
    return None
