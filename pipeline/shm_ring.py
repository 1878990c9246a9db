"""Shared-memory slot pools: fixed slots for frames and other large arrays between processes.

A :class:`SlotPool` is one ``multiprocessing.shared_memory`` segment cut into ``slots``
slots of ``slot_bytes`` bytes, preceded by one int32 reference count per slot. Any process
that attached the pool can take a free slot (:meth:`SlotPool.acquire`, which waits, with a
timeout between checks of the stop flag, while every slot is held), write into it and pass
it on by reference: a message names the pool, the slot, the offset, shape, strides and
dtype of each array (:mod:`sffscan.pipeline.wire`); nothing is pickled or copied again.

Release is by reference count, the way numpy arrays live: a slot's count is raised once
for every message that carries it, and every array a receiver makes from it holds one
``memoryview`` of the slot whose finaliser lowers the count when the last view (slices
included) is gone. A slot returns to the pool when its count reaches zero. The counts live
in the segment and change under one ``multiprocessing`` lock per pool; a semaphore counts
the free slots.

Lifetime: the creator unlinks every segment as soon as the workers have attached
(:meth:`SlotPool.unlink`), so after that no name is left in ``/dev/shm`` whatever happens
to the processes (the mapping lives as long as a process holds it); before that, Python's
resource tracker unlinks it if the creator dies.

Memory: ``slots * slot_bytes`` bytes per pool (plus 64 bytes of counts per 16 slots),
fixed at creation, whatever the scan length.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from multiprocessing import shared_memory
from typing import Any

import numpy as np

#: arrays inside a slot start on this boundary, bytes
ALIGN = 64
#: a wait for a free slot longer than this means the slots leak or the ring is too small
STARVED_S = 60.0
#: a count update waiting longer than this for the lock means its holder died
LOCK_S = 10.0
_MADV_POPULATE_READ = 22  # linux/mman.h; not in Python 3.11's mmap module
_MADV_POPULATE_WRITE = 23


class PoolStopped(Exception):
    """Raised in a wait for a free slot when the pipeline is stopping."""


def map_now(shm: shared_memory.SharedMemory, *, write: bool) -> None:
    """Map every page of ``shm`` now (Linux >= 5.14; elsewhere nothing), not at each
    page's first use while streaming: a page fault per 4 KiB of a frame costs about as much
    as copying the frame. ``write``: the pages are written here (the creator)."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        shm._mmap.madvise(_MADV_POPULATE_WRITE if write  # type: ignore[attr-defined]
                          else _MADV_POPULATE_READ)


def aligned(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


@dataclass(frozen=True)
class PoolSpec:
    """What a process needs to attach a pool (JSON-able)."""

    name: str
    slots: int
    slot_bytes: int
    label: str
    #: message types (:mod:`sffscan.pipeline.wire` ``t``) whose arrays are copied into it
    kinds: tuple[str, ...] = ()

    @property
    def header_bytes(self) -> int:
        return aligned(4 * self.slots)

    @property
    def total_bytes(self) -> int:
        return self.header_bytes + self.slots * self.slot_bytes

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> PoolSpec:
        return cls(d["name"], d["slots"], d["slot_bytes"], d["label"], tuple(d["kinds"]))


def new_spec(label: str, *, slots: int, slot_bytes: int,
             kinds: tuple[str, ...] = ()) -> PoolSpec:
    """A spec with a fresh segment name ``sffscan-<pid>-<label>-<random>``."""
    if slots < 1 or slot_bytes < 1:
        raise ValueError(f"pool '{label}': slots and slot_bytes must be >= 1, got "
                         f"{slots}, {slot_bytes}")
    name = f"sffscan-{os.getpid()}-{label}-{secrets.token_hex(4)}"
    return PoolSpec(name, slots, aligned(slot_bytes), label, tuple(kinds))


class SlotPool:
    """Fixed slots in one shared-memory segment, with per-slot reference counts.

    Parameters
    ----------
    spec : PoolSpec
    sync : (multiprocessing Lock, multiprocessing Semaphore)
        Shared by every process using the pool (passed to the workers at start): the lock
        guards the counts, the semaphore counts the free slots (its initial value must be
        ``spec.slots``). No condition variable: a process that dies while waiting must not
        leave the others blocked.
    create : bool
        Create the segment (the coordinating process) or attach to it (a worker).
    """

    def __init__(self, spec: PoolSpec, sync: tuple[Any, Any], *, create: bool) -> None:
        self.spec = spec
        self.lock, self.free = sync
        self.shm = shared_memory.SharedMemory(name=spec.name, create=create,
                                              size=spec.total_bytes if create else 0)
        self._unlinked = not create
        map_now(self.shm, write=create)
        self.refs = np.ndarray((spec.slots,), np.int32, buffer=self.shm.buf)
        if create:
            self.refs[:] = 0
        base = self.refs.__array_interface__["data"][0]
        self._data0 = base + spec.header_bytes
        self._data1 = self._data0 + spec.slots * spec.slot_bytes
        self.waited_s = 0.0
        self.acquired = 0
        self._closed = False

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        if not self.lock.acquire(timeout=LOCK_S):
            raise RuntimeError(f"shared-memory ring '{self.spec.label}': its lock was not "
                               f"released within {LOCK_S:g} s (a process died holding it)")
        try:
            yield
        finally:
            self.lock.release()

    # -- slots ---------------------------------------------------------------------------
    def acquire(self, stop: Callable[[], bool], *, wait_s: float = 0.25) -> int:
        """Take a free slot (count 1); wait while all are held, checking ``stop``."""
        t0 = time.perf_counter()
        while not self.free.acquire(timeout=wait_s):
            if stop():
                raise PoolStopped(self.spec.label)
            if time.perf_counter() - t0 > STARVED_S:
                raise RuntimeError(
                    f"shared-memory ring '{self.spec.label}': all {self.spec.slots} slots "
                    f"held for {STARVED_S:g} s (a stage holds more frames than the ring "
                    "was sized for)")
        with self._locked():
            i = int(np.flatnonzero(self.refs == 0)[0])
            self.refs[i] = 1
        self.acquired += 1
        self.waited_s += time.perf_counter() - t0
        return i

    def incref(self, slot: int) -> None:
        with self._locked():
            if self.refs[slot] <= 0:
                raise RuntimeError(f"ring '{self.spec.label}': slot {slot} is not held")
            self.refs[slot] += 1

    def decref(self, slot: int) -> None:
        if self._closed:
            return
        with self._locked():
            self.refs[slot] -= 1
            freed = self.refs[slot] == 0
        if freed:
            self.free.release()

    def held(self) -> int:
        """Slots held now."""
        with self._locked():
            return int(np.count_nonzero(self.refs))

    def slot_view(self, slot: int) -> np.ndarray:
        """The bytes of one slot (uint8); the slot's count must already include it, and
        is lowered once this array and every array made from it are gone."""
        off = self.spec.header_bytes + slot * self.spec.slot_bytes
        buf = self.shm.buf
        assert buf is not None
        holder = np.frombuffer(buf[off:off + self.spec.slot_bytes], np.uint8)
        # numpy keeps the memoryview it made as the base of every view of ``holder``
        fin = weakref.finalize(holder.base, self.decref, slot)
        fin.atexit = False  # at interpreter exit the segment may be gone already
        return holder

    def array(self, slot: int, *, offset: int, shape: tuple[int, ...], dtype: str,
              strides: tuple[int, ...] | None = None) -> np.ndarray:
        """An array in ``slot`` that holds one count of it until the array (and every view
        of it) is gone."""
        return np.ndarray(shape, np.dtype(dtype), buffer=self.slot_view(slot), offset=offset,
                          strides=strides)

    def locate(self, arr: np.ndarray) -> tuple[int, int] | None:
        """(slot, offset) of an array lying inside one slot of this pool, else None."""
        addr = arr.__array_interface__["data"][0]
        if not self._data0 <= addr < self._data1:
            return None
        slot, offset = divmod(addr - self._data0, self.spec.slot_bytes)
        lo, hi = _extent(arr)
        if offset + lo < 0 or offset + hi > self.spec.slot_bytes:
            return None
        return int(slot), int(offset)

    # -- lifetime ------------------------------------------------------------------------
    def unlink(self) -> None:
        """Remove the segment's name (the mappings stay valid); the creator calls it once
        every worker has attached."""
        if not self._unlinked:
            self._unlinked = True
            self.shm.unlink()

    def close(self) -> None:
        """Unmap the segment if no array of it is alive (else it goes at process exit)."""
        self.unlink()
        self._closed = True
        del self.refs
        try:
            self.shm.close()
        except BufferError:  # arrays still alive in this process: unmapped at exit
            pass


def _extent(arr: np.ndarray) -> tuple[int, int]:
    """Byte range [lo, hi) an array covers relative to its first element."""
    lo = hi = 0
    for n, s in zip(arr.shape, arr.strides, strict=True):
        if n == 0:
            return 0, 0
        if s >= 0:
            hi += (n - 1) * s
        else:
            lo += (n - 1) * s
    return lo, hi + arr.itemsize
