"""Whole files written past the kernel's page cache (``O_DIRECT``): a recording's frames.

Why: a recorder writes every raw frame once (about 1.5 MB compressed at 1280 x 1024,
10-bit, 150 frames/s) and reads none of them back during the scan. Through the page cache
each frame is first copied into cache pages by the writing process, and on the 2-core
development VM (a virtual machine whose balloon driver reports freed pages to the host:
perf shows ``page_reporting_*`` and ``clear_page_erms`` wherever memory is handed out
anew, so new cache pages are expensive there) that copy cost more than the frame's
compression: perf of a scan with the recorder on (600 frames, processes) put 7.6 %
of all the processes' CPU, half of the recorder's, in the kernel's
``copy_folio_from_iter_atomic``. Measured there
(2026-12-04, ``bench/bench_parallel.py --recorder-io unbuffered,page-cache``, 3 rounds
interleaved, bench/results/parallel_default_results.md): the recorder's own CPU 5.2 -> 3.2
ms a frame in processes (5.5 -> 3.2 in threads); frames/s with the recorder on 90.9 -> 91.6
in processes (faster in each of the 3 pairs) and 70.1 -> 89.0 in threads. The writer alone
(``bench/bench_recorder.py --sections writer --keep-runs``, Blosc LZ4, 300 frames):
4.0 -> 3.2 ms a frame with every run's recording kept (the cache grows, as under a long
recording; uncompressed frames 7.9 -> 1.7), about the same (3.3 -> 3.5) where each run's
recording is deleted before the next, whose pages the cache then reuses
(bench/results/recorder_io_kept.md, recorder_io.md). Writing past the cache also keeps a
long recording from filling memory with dirty pages that the kernel writes back in bursts.
The price: each write waits for the device (about 1 ms for a frame on the VM's disk), and
a disk slower than the stream is no longer hidden for a while by the cache (a short scan
on a slow disk would fit in the cache): so the recorder goes back to the page cache for the
rest of a recording when it falls behind while waiting for the disk
(:class:`~sffscan.pipeline.formats.recorder_sink.RecorderSink`); the writer's
``page_cache=True`` writes through it from the start.

How: the file's bytes are copied into a page-aligned buffer that is reused from file to
file, padded to a multiple of :data:`ALIGN` bytes, written with ``O_DIRECT``, and the file
is truncated to its true length. The file holds exactly the bytes given (tested against a
plain write). Where the platform has no ``O_DIRECT`` (macOS, Windows) or the file system
refuses it (tmpfs before Linux 6.6: ``EINVAL`` when the file is opened; a device whose
logical block is larger than :data:`ALIGN`: ``EINVAL`` at the first write),
:meth:`UnbufferedFiles.write` returns False and the caller writes the file the usual way;
a refusal is remembered per file system, so it costs one attempt. Small files (below
``min_bytes``: a frame's header row) are left to the page cache: each unbuffered write
waits for the device.

What it does not change: the durability the recorder promises comes from its fsyncs (the
file's size and folder entry are metadata, which ``O_DIRECT`` does not make durable).
"""

from __future__ import annotations

import errno
import mmap
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["ALIGN", "UnbufferedFiles"]

#: alignment of the buffer, of the file offsets and of the lengths written, bytes (the
#: page size, and a multiple of every common device's logical block: 512 or 4096)
ALIGN = 4096


class UnbufferedFiles:
    """Writes whole new files past the page cache where the file system allows it.

    Parameters
    ----------
    min_bytes : int, keyword-only
        Files smaller than this are not written here (:meth:`write` returns False).

    Notes
    -----
    One buffer, reused: one thread writes at a time (the recorder's).

    Attributes
    ----------
    written : int
        Files written past the page cache.
    refused : int
        Files that a file system's refusal sent back to the caller.
    wait_s : float
        Wall time spent in the writes themselves (waiting for the device), s.
    """

    def __init__(self, *, min_bytes: int = 1 << 18) -> None:
        if min_bytes < 0:
            raise ValueError(f"min_bytes must be >= 0, got {min_bytes}")
        self.min_bytes = min_bytes
        self.written = 0
        self.refused = 0
        self.wait_s = 0.0
        self._buf: mmap.mmap | None = None
        self._refusing: set[int] = set()  # st_dev of the file systems that refused

    def _buffer(self, size: int) -> mmap.mmap:
        """The page-aligned buffer, at least ``size`` bytes (grown by whole MiB)."""
        if self._buf is None or len(self._buf) < size:
            if self._buf is not None:
                self._buf.close()
            self._buf = mmap.mmap(-1, -(-size // (1 << 20)) << 20)
        return self._buf

    def write(self, path: str | Path, parts: Sequence[Any]) -> bool:
        """Create ``path`` (it must not exist) holding ``parts`` (bytes-like) one after the
        other, past the page cache.

        Returns
        -------
        bool
            True when written; False when the caller must write it the usual way (no
            ``O_DIRECT`` here, the file system refuses it, or the file is small): then
            nothing was created.

        Raises
        ------
        OSError
            Any other failure (disk full, permissions); the partial file is removed.
        """
        flag = getattr(os, "O_DIRECT", 0)
        views = [memoryview(p).cast("B") for p in parts]
        n = sum(v.nbytes for v in views)
        if not flag or n < self.min_bytes or n == 0:
            return False
        path = Path(path)
        dev = os.stat(path.parent).st_dev
        if dev in self._refusing:
            self.refused += 1
            return False
        size = -(-n // ALIGN) * ALIGN
        buf = self._buffer(size)
        at = 0
        for v in views:
            buf[at:at + v.nbytes] = v
            at += v.nbytes
        buf[n:size] = bytes(size - n)  # the slack beyond the end: no bytes of an older file
        try:
            # 0o666 less the umask: the permissions open(path, "wb") gives
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | flag, 0o666)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
            self._refusing.add(dev)
            self.refused += 1
            return False
        done = 0
        t0 = time.perf_counter()
        try:
            with memoryview(buf) as whole:
                while done < size:
                    k = os.pwrite(fd, whole[done:size], done)
                    if k <= 0 or k % ALIGN:
                        raise OSError(errno.EIO, f"short unbuffered write ({k} of "
                                                 f"{size - done} bytes)", str(path))
                    done += k
            os.ftruncate(fd, n)
        except OSError as exc:
            self.wait_s += time.perf_counter() - t0
            os.close(fd)
            path.unlink(missing_ok=True)
            if exc.errno == errno.EINVAL and done == 0:  # the device's block is larger
                self._refusing.add(dev)
                self.refused += 1
                return False
            raise
        os.close(fd)
        self.wait_s += time.perf_counter() - t0
        self.written += 1
        return True

    def close(self) -> None:
        """Release the buffer (a later :meth:`write` makes a new one)."""
        if self._buf is not None:
            self._buf.close()
            self._buf = None
