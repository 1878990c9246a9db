"""Stages and child processes for tests/pipeline/test_parallel.py and
tests/pipeline/test_parallel_scan.py
(kept free of pytest, so that worker processes and child scans start fast)."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
from sffscan.stages.messages import Frame, FrameHeader
from sffscan.stages.protocol import Stage


def shm_names(pid: int | None = None) -> list[str]:
    """The shared-memory blocks of sffscan in /dev/shm (of process ``pid`` only, if given)."""
    prefix = f"sffscan-{pid}-" if pid is not None else "sffscan-"
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(prefix))


class FrameNumbers(Stage):
    """Source: ``n`` small uint16 frames whose pixels all equal their frame_id."""

    name = "numbers"

    def __init__(self, n: int, shape: tuple[int, int] = (16, 24)) -> None:
        self.n = n
        self.shape = shape

    def produce(self) -> Iterator[Frame]:
        for i in range(self.n):
            hdr = FrameHeader(frame_id=i, timestamp_ns=i, focus_index=0)
            yield Frame(hdr, np.full(self.shape, i, np.uint16))


class Explode(Stage):
    """Passes frames on; raises ValueError at frame ``at``."""

    name = "explode"

    def __init__(self, at: int) -> None:
        self.at = at

    def process(self, item: Frame) -> Iterator[Frame]:
        if item.header.frame_id == self.at:
            raise ValueError(f"frame_id {self.at}: boom")
        yield item


class Collect(Stage):
    """Tail: keeps the frame ids and pixel sums it got; records how it was closed."""

    name = "collect"

    def __init__(self) -> None:
        self.ids: list[int] = []
        self.sums: list[int] = []
        self.corners: list[tuple[int, int]] = []  # pixels (0, 0) and (0, 1)
        self.closed: bool | None = None

    def process(self, item: Frame) -> Iterator[None]:
        self.ids.append(item.header.frame_id)
        self.sums.append(int(item.image.sum()))
        self.corners.append((int(item.image[0, 0]), int(item.image[0, 1])))
        return iter(())

    def close(self, *, failed: bool) -> None:
        self.closed = failed


def explode_group(at: int) -> list[Stage]:
    """Worker factory: one stage that fails at frame ``at``."""
    return [Explode(at)]


def pass_group() -> list[Stage]:
    """Worker factory: one stage that passes every frame on."""
    return [Explode(at=-1)]


class OpenCVThreads(Stage):
    """Writes this process's ``cv2.getNumThreads()`` into pixel (0, ``col``) of each frame
    (a copy; the other pixels kept)."""

    def __init__(self, col: int = 0, name: str = "opencv_threads") -> None:
        self.col = col
        self.name = name

    def process(self, item: Frame) -> Iterator[Frame]:
        import cv2

        image = np.array(item.image)
        image[0, self.col] = cv2.getNumThreads()
        yield Frame(item.header, image)


def opencv_threads_group() -> list[Stage]:
    """Worker factory: one :class:`OpenCVThreads` stage."""
    return [OpenCVThreads()]


class ThreadMark(Stage):
    """Writes the low 32 bits of its thread's id into pixels (0, 0) and (0, 1) of each frame
    (a copy)."""

    name = "thread_mark"

    def process(self, item: Frame) -> Iterator[Frame]:
        ident = threading.get_ident()
        image = np.array(item.image)
        image[0, 0], image[0, 1] = ident & 0xFFFF, (ident >> 16) & 0xFFFF
        yield Frame(item.header, image)


class SameThread(Stage):
    """Writes into pixel (0, 0) whether it runs in the thread :class:`ThreadMark` marked
    (1 or 0), and 0 into (0, 1)."""

    name = "same_thread"

    def process(self, item: Frame) -> Iterator[Frame]:
        ident = threading.get_ident()
        image = np.array(item.image)
        same = (int(image[0, 0]), int(image[0, 1])) == (ident & 0xFFFF, (ident >> 16) & 0xFFFF)
        image[0, 0], image[0, 1] = int(same), 0
        yield Frame(item.header, image)


def thread_mark_group() -> list[Stage]:
    """Worker factory: :class:`ThreadMark` then :class:`SameThread`."""
    return [ThreadMark(), SameThread()]


def failing_focus_group(cfg: dict[str, Any], at: int) -> list[Stage]:
    """Worker factory: the scan's focus measure and depth stages; depth fails at frame
    ``at`` with a FrameError (as for a frame it cannot place)."""
    from sffscan.pipeline.scan_processes import focus_group
    from sffscan.stages.messages import FocusFrame, FrameError

    fm, depth = focus_group(cfg)
    real = depth.process

    def process(item: FocusFrame) -> Any:
        if item.placed.header.frame_id == at:
            raise FrameError(f"frame_id {at}: injected failure")
        return real(item)

    depth.process = process  # type: ignore[method-assign]
    return [fm, depth]


def run_cli(argv: list[str]) -> Any:
    """``sffscan ARGV`` as a child process's whole life."""
    from sffscan.pipeline.cli.main import main

    raise SystemExit(main(argv))


if __name__ == "__main__":
    run_cli(sys.argv[1:])
