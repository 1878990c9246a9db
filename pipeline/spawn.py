"""The life of a spawned helper process, written once for the stage workers and the
simulator's render workers.

The main process starts its helpers with the ``spawn`` context (no fork of a process with
torch or OpenCV threads), gives each the read end of a stop pipe (:class:`StopPipes`),
and at the end joins them, terminating and then killing what has not left within
:data:`JOIN_TIMEOUT_S` (:func:`join_or_kill`). A helper dies with the main process:
it asks the kernel for SIGKILL when its parent dies (:func:`die_with_parent`), and its
:func:`watch_stop` thread leaves at once when the pipe reaches end of file or
``os.getppid()`` changes. Ctrl-C is the main process's to handle: helpers ignore SIGINT.
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

log = logging.getLogger(__name__)

#: longest single wait before a stop flag is checked again, s
WAIT_S = 0.25
#: longest wait for a helper to import and build what it runs, s
START_TIMEOUT_S = 300.0
#: how long a helper gets to finish after the stop order before it is terminated, s
JOIN_TIMEOUT_S = 10.0
_PR_SET_PDEATHSIG = 1


def spawn_context() -> Any:
    """The ``multiprocessing`` context every helper process is started with."""
    return mp.get_context("spawn")


class StopPipes:
    """The main process's stop order to its helpers: one pipe each (a helper watches its
    read end, :func:`watch_stop`; end of file there means the main process died)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._writers: list[Any] = []
        self._readers: list[Any] = []

    def pipe(self, ctx: Any) -> Any:
        """A new pipe; its read end goes to one helper's arguments."""
        r, w = ctx.Pipe(duplex=False)
        self._readers.append(r)
        self._writers.append(w)
        return r

    def started(self) -> None:
        """The helpers have their read ends: close ours."""
        for r in self._readers:
            r.close()
        self._readers.clear()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        """Send the stop order (once)."""
        if self.event.is_set():
            return
        self.event.set()
        for w in self._writers:
            with contextlib.suppress(OSError):
                w.send_bytes(b"stop")

    def close(self) -> None:
        self.started()
        for w in self._writers:
            w.close()
        self._writers.clear()


def join_or_kill(procs: Iterable[tuple[str, Any]], timeout_s: float = JOIN_TIMEOUT_S) -> None:
    """Join the started ``(label, process)`` pairs within ``timeout_s`` in all; terminate
    (then kill) any that is left, with a warning naming it."""
    deadline = time.monotonic() + timeout_s
    for label, proc in procs:
        if proc.pid is None:  # never started
            continue
        proc.join(max(0.1, deadline - time.monotonic()))
        if proc.is_alive():
            log.warning("process %s did not stop within %g s: terminated", label, timeout_s)
            proc.terminate()
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(5.0)


def die_with_parent(parent: int) -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before prctl: leave now
        os._exit(1)


def helper_start(parent: int) -> None:
    """What every helper does first: die with ``parent``, leave Ctrl-C to it, and dump
    its stacks on ``kill -USR1 <pid>``."""
    die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    faulthandler.register(signal.SIGUSR1)


def watch_stop(control: Any, parent: int, on_stop: Callable[[], None],
               done: threading.Event) -> threading.Thread:
    """Start a thread that calls ``on_stop`` when the main process writes to ``control``
    (the read end of a :class:`StopPipes` pipe) and ends this process when the main
    process is gone (end of file, or ``os.getppid()`` changed); it returns when ``done``
    is set. Every wait is 0.5 s at most."""

    def watch() -> None:
        while not done.is_set():
            try:
                if not control.poll(0.5):
                    if os.getppid() != parent:
                        os._exit(1)
                    continue
                control.recv_bytes()
            except (EOFError, OSError):  # the main process is gone: nothing to report to
                os._exit(1)
            on_stop()
            return

    t = threading.Thread(target=watch, name="stop-watch", daemon=True)
    t.start()
    return t
