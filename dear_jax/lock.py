"""One run per workdir: `<workdir>/run.lock` names the process that runs there.

The file holds the owner's pid, host name and process start time (from /proc, where there is
one). A second run on the workdir is refused while that process lives; once it is gone (killed,
machine rebooted) the next run takes the lock over and says so. A lock taken on another host
cannot be checked from here: the message says which file to delete if that run is over.
The file is created whole (written to a temporary name, then hard-linked into place), so a
reader never sees half of it.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import pathlib
import socket

log = logging.getLogger(__name__)

LOCK_NAME = "run.lock"


class WorkdirLocked(RuntimeError):
    """Another live process runs in this workdir."""


def _start_time(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (tells a reused pid apart)."""
    try:
        stat = pathlib.Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # field 22; the name in () may contain spaces


def _alive(holder: dict) -> bool:
    pid = int(holder.get("pid", -1))
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    started = holder.get("start_time")
    return started is None or _start_time(pid) in (None, started)


def held(workdir: str | os.PathLike) -> bool:
    """Whether a run holds `workdir` now: its lock names a live process of this host, or a
    process of another host (which cannot be checked from here)."""
    holder = WorkdirLock(workdir)._read()
    if not holder:
        return False
    return holder.get("host") not in (None, socket.gethostname()) or _alive(holder)


class WorkdirLock:
    """Context manager holding `<workdir>/run.lock`; re-entrant within one process. Process
    `process` > 0 of a multi-host run (`jax.distributed`) holds `run.<process>.lock`."""

    def __init__(self, workdir: str | os.PathLike, process: int = 0):
        name = LOCK_NAME if process == 0 else f"run.{process}.lock"
        self.path = pathlib.Path(workdir) / name
        self._owned = False

    def _read(self) -> dict | None:
        try:
            return json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}  # unreadable: treated as stale

    def acquire(self) -> None:
        me = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "start_time": _start_time(os.getpid()),
            "since": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{LOCK_NAME}.{me['pid']}")
        tmp.write_text(json.dumps(me))
        try:
            for _ in range(3):
                try:
                    os.link(tmp, self.path)
                    self._owned = True
                    return
                except FileExistsError:
                    pass
                holder = self._read()
                if holder is None:
                    continue  # released meanwhile
                if holder.get("pid") == me["pid"] and holder.get("host") == me["host"]:
                    return  # this process holds it already
                where = f"pid {holder.get('pid')} on host {holder.get('host')}"
                if holder.get("host") not in (None, me["host"]):
                    raise WorkdirLocked(
                        f"workdir {self.path.parent} is in use by {where} (since "
                        f"{holder.get('since')}); this host cannot check that process. If that run "
                        f"is over, delete {self.path}; otherwise use another --workdir"
                    )
                if _alive(holder):
                    raise WorkdirLocked(
                        f"workdir {self.path.parent} is in use by {where} (since "
                        f"{holder.get('since')}); stop that run first or use another --workdir"
                    )
                log.warning(
                    "taking over %s: its run (%s, since %s) is no longer running",
                    self.path,
                    where,
                    holder.get("since"),
                )
                self._remove_stale(holder, tmp.with_suffix(".stale"))
            raise WorkdirLocked(f"could not take {self.path}: other runs keep taking it")
        finally:
            tmp.unlink(missing_ok=True)

    def _remove_stale(self, holder: dict, aside: pathlib.Path) -> None:
        """Remove the lock file if it still names `holder`: moved aside first (a rename is atomic,
        so of two runs taking over at once one moves it), then deleted; a lock another run took
        meanwhile goes back in place."""
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return  # another run moved it first
        try:
            moved = json.loads(aside.read_text())
        except (OSError, ValueError):
            moved = {}
        if moved != holder and moved:
            try:
                os.link(aside, self.path)  # a live run's lock: restored
            except FileExistsError:
                pass
        aside.unlink(missing_ok=True)

    def release(self) -> None:
        if self._owned:
            holder = self._read()
            if holder and holder.get("pid") == os.getpid():
                self.path.unlink(missing_ok=True)
            self._owned = False

    def __enter__(self) -> WorkdirLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
