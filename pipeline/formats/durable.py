"""Durability of a recording: fsync the files written since the last sync, and their folders.

Zarr's local store writes every file atomically (a temporary file, then a rename), which
protects against a killed process but not against a power cut: the data and the rename can
still be in the page cache. :class:`SyncTracker` collects the files a writer touched and,
at most every ``interval_s`` seconds (and at close), fsyncs each of them and then each
folder holding them (the folder's entry makes a rename durable). A power cut then loses at
most ``interval_s`` of the stream.

Why not ``os.sync()``: it flushes every file system of the machine, for every process.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

#: reserve kept beside a recording while it is written, bytes: freed on a disk-full error so
#: the metadata and the 'failed' status can still be written
RESERVE_BYTES = 256 * 2**10
RESERVE_NAME = ".sffscan-reserve"


def fsync_path(path: Path, *, directory: bool = False) -> None:
    """fsync one file or folder; a file that is not there (yet) is skipped."""
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class SyncTracker:
    """Files written since the last sync; :meth:`sync` makes them durable."""

    def __init__(self, root: Path, *, interval_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.root = root
        self.interval_s = interval_s
        self.clock = clock
        self.pending: set[Path] = set()
        self.last = clock()
        self.syncs = 0

    def add(self, rel: str | Iterable[str]) -> None:
        """Note files (relative to the root) that were written."""
        if isinstance(rel, str):
            self.pending.add(self.root / rel)
        else:
            self.pending.update(self.root / r for r in rel)

    def due(self) -> bool:
        return bool(self.pending) and self.clock() - self.last >= self.interval_s

    def sync(self) -> None:
        """fsync every pending file, then the folders holding them (deepest first)."""
        folders: set[Path] = set()
        for path in sorted(self.pending):
            fsync_path(path)
            folders.add(path.parent)
        # the folders up to the root: a new sub-folder's entry lives in its parent
        for folder in list(folders):
            while folder != self.root and self.root in folder.parents:
                folder = folder.parent
                folders.add(folder)
        folders.add(self.root)
        folders.add(self.root.parent)
        for folder in sorted(folders, key=lambda f: len(f.parts), reverse=True):
            fsync_path(folder, directory=True)
        self.pending.clear()
        self.last = self.clock()
        self.syncs += 1


def make_reserve(root: Path, size: int = RESERVE_BYTES) -> Path:
    """A file of ``size`` bytes (really allocated) inside ``root``."""
    path = root / RESERVE_NAME
    with open(path, "wb") as fh:
        fh.write(b"\0" * size)
    return path


def free_reserve(root: Path) -> bool:
    """Delete the reserve; True if there was one."""
    try:
        (root / RESERVE_NAME).unlink()
        return True
    except FileNotFoundError:
        return False
