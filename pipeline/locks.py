"""Exclusive writers: an OS lock on a mosaic (or a recording) while it is written.

The lock is :func:`fcntl.flock` on a small file beside the store, ``<name>.lock`` (beside, not
inside: replacing a mosaic empties its folder). The file holds the writer's host, pid, start
time and command line, so a refused writer names the holder. The kernel releases the lock
when its holder dies (kill -9, power cut): a lock file left behind is stale, detected as
such (its lock is free) and taken over with a warning. The holder removes the file when it
is done; a writer that opened a file being removed sees that its inode is no longer the
path's and opens the new one, so two writers never hold the lock at once.

On a shared file system the lock is as good as its ``flock`` (NFS v4: yes; old NFS: local
to each machine).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import logging
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sffscan.pipeline.config import ConfigError

log = logging.getLogger(__name__)

#: attempts to lock a file that was replaced meanwhile (each one is a race lost, not a wait)
_ATTEMPTS = 8
#: pause before retrying a lock that a probe of a stale lock file holds for a moment, s
_PROBE_S = 0.02


class LockHeld(ConfigError):
    """Another writer holds the lock; ``holder`` is what its lock file says about it."""

    def __init__(self, message: str, holder: dict[str, Any]) -> None:
        super().__init__(message)
        self.holder = holder


def lock_path(path: str | Path) -> Path:
    """The lock file of the store at ``path``: ``<name>.lock`` beside it (symbolic links and
    relative spellings resolved, so every spelling of one store has one lock)."""
    p = Path(path).resolve()
    return p.parent / f"{p.name}.lock"


def describe_holder(holder: dict[str, Any]) -> str:
    """``host pid N (since T: command)``, or ``an unknown process``."""
    if not holder:
        return "an unknown process (its lock file is empty)"
    text = f"{holder.get('host', '?')} pid {holder.get('pid', '?')}"
    extra = ", ".join(str(holder[k]) for k in ("since", "command") if holder.get(k))
    return f"{text} ({extra})" if extra else text


def _read(fd: int) -> dict[str, Any]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        raw = os.read(fd, 65536)
        data = json.loads(raw.decode("utf-8")) if raw.strip() else {}
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _alive(holder: dict[str, Any]) -> bool:
    """False only when the holder is known dead: a pid of this host that does not exist."""
    if holder.get("host") != socket.gethostname() or not isinstance(holder.get("pid"), int):
        return True
    try:
        os.kill(holder["pid"], 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


@dataclass
class WriterLock:
    """A held lock; :meth:`release` (or leaving the ``with`` block) frees it."""

    target: Path
    file: Path
    fd: int | None

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            if _same_file(self.fd, self.file):
                self.file.unlink()  # while still holding it: see the module notes
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> WriterLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def acquire(path: str | Path, *, what: str = "mosaic") -> WriterLock:
    """Lock the store at ``path`` for writing, or raise :class:`LockHeld` naming the holder.

    Raises
    ------
    LockHeld
        Another writer (this machine or another) holds the lock.
    ConfigError
        The lock file cannot be created (the message names it).
    """
    target = Path(path)
    file = lock_path(target)
    for _ in range(_ATTEMPTS):
        try:
            fd = os.open(file, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise ConfigError(f"{what} {target}: cannot create its lock file {file} "
                              f"({err.strerror or err})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read(fd)
            os.close(fd)
            if not _alive(holder):  # a probe (:func:`holder`) of a stale file, for a moment
                time.sleep(_PROBE_S)
                continue
            raise LockHeld(f"{what} {target}: being written by {describe_holder(holder)} "
                           f"(lock {file}); wait for it to end, or stop it", holder) from None
        except OSError as err:
            os.close(fd)
            raise ConfigError(f"{what} {target}: cannot lock {file} ({err.strerror or err})"
                              ) from None
        if not _same_file(fd, file):  # removed or replaced by its holder meanwhile: again
            os.close(fd)
            continue
        stale = _read(fd)
        if stale:
            log.warning("%s %s: a stale lock of %s (no longer running) taken over", what,
                        target, describe_holder(stale))
        me = {"host": socket.gethostname(), "pid": os.getpid(),
              "since": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
              "command": " ".join(sys.argv)[:300]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me).encode("utf-8"), 0)
        return WriterLock(target, file, fd)
    raise ConfigError(f"{what} {target}: its lock file {file} kept being replaced; another "
                      "writer is starting, try again")


def holder(path: str | Path) -> dict[str, Any] | None:
    """What the lock file of the store at ``path`` says of its holder while the lock is held
    (possibly ``{}``), None when nobody holds it (no lock file, or a stale one)."""
    file = lock_path(path)
    try:
        fd = os.open(file, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:  # a writer meeting this probe retries (see acquire)
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read(fd)
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def claim_mosaic(path: str | Path, *, overwrite: bool) -> WriterLock:
    """The lock of a new mosaic at ``path`` for a tool that computes before it writes
    (``stack``, ``stop-and-go``): the folders above it made (as the mosaic writer makes
    them), the lock taken, then the path checked as the writer will check it, so that a
    second writer or an existing output is refused before any work, not after it.

    Raises
    ------
    LockHeld
        Another writer (a scan, a stack, a stop-and-go run) holds the lock.
    FileExistsError
        ``path`` exists and ``overwrite`` is false, or it is not a mosaic nor an empty
        folder (the message names it).
    ConfigError
        The folders or the lock file cannot be created (the message names them).
    """
    from sffscan.pipeline.mosaic.writer import check_replaceable

    target = Path(path)
    try:
        target.resolve().parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"mosaic {target}: cannot create its folder "
                          f"({err.strerror or err})") from None
    held = acquire(target, what="mosaic")
    try:
        check_replaceable(target, overwrite=overwrite)
    except BaseException:
        held.release()
        raise
    return held
