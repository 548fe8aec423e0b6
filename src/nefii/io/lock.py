"""``RUN/run.lock``: one writer per run folder.

Created with ``O_CREAT | O_EXCL`` (atomic on local file systems) and holding the writer's pid, host, verb
and start time. A second writer is refused with a line naming the holder. A lock left by a process that is
gone (same host, pid no longer running: a kill -9, a power cut) is stale and taken over with a warning.
"""
from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import InputError

LOCK_FILE = "run.lock"


@dataclass(frozen=True)
class Holder:
    pid: int
    host: str
    verb: str
    since: str

    def describe(self) -> str:
        return f"nefii {self.verb} (pid {self.pid} on {self.host}, since {self.since})"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def _read_holder(path: Path) -> Holder | None:
    try:
        d = json.loads(path.read_text())
        return Holder(int(d["pid"]), str(d["host"]), str(d["verb"]), str(d["since"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


class RunLock:
    """Hold ``folder/run.lock`` while writing ``folder`` (a context manager; released on any exit)."""

    def __init__(self, folder: Path, verb: str) -> None:
        self.path = folder / LOCK_FILE
        self.holder = Holder(os.getpid(), socket.gethostname(), verb, time.strftime("%Y-%m-%d %H:%M:%S"))
        self.held = False

    def acquire(self, warn: Callable[[str], None] = lambda s: None) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                other = _read_holder(self.path)
                if other is None:
                    if time.time() - self.path.stat().st_mtime < 10.0:   # being written this instant
                        raise InputError(self.path.parent, "another nefii process is starting to write here") from None
                    warn(f"taking over {self.path}: unreadable, left by a process that is gone")
                elif other.host == self.holder.host and not _alive(other.pid):
                    warn(f"taking over {self.path} from {other.describe()}, which is no longer running")
                else:
                    raise InputError(self.path.parent, f"in use by {other.describe()}; wait for it to finish or use "
                                                       f"another --out (if that process is gone, delete {self.path})")
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(self.holder.__dict__, f)
            self.held = True
            return
        raise InputError(self.path.parent, "another nefii process took the lock at the same time")

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
