"""One progress display for every long command (scan, demo, replay, stopgo).

On a terminal it is a `tqdm <https://tqdm.github.io>`_ bar: items done of the total, the
rate, the elapsed time and the time left, redrawn in place. On anything else (a pipe, a
log file, a notebook's captured stream) it never writes a carriage return: it writes one
plain line every ``every_s`` seconds (the first at once) with the same information, from
tqdm's own formatter, so the two read alike::

    frames 120/455 (26.4 %)  30.1 frames/s  elapsed 00:04  eta 00:11, acquired 130

A stream that fails (a closed pipe or terminal) switches the display off; it never stops
the work it reports on.
"""

from __future__ import annotations

import io
import math
import os
import sys
import time
from typing import TYPE_CHECKING, TextIO

from tqdm import tqdm

if TYPE_CHECKING:
    from sffscan.pipeline.stats import StageStats

__all__ = ["PLAIN_FORMAT", "SLOW_FORMAT", "ProgressDisplay", "ScanProgress", "is_terminal",
           "terminal_columns"]

#: tqdm ``bar_format`` of the plain lines (no bar, no carriage return), at one item per
#: second or more. ``rate_noinv``: tqdm's own ``rate`` field turns into seconds per item
#: below one item per second, which this line would print as items per second.
PLAIN_FORMAT = ("{desc} {n_fmt}/{total_fmt} ({percentage:.1f} %)  {rate_noinv:.1f} {unit}/s  "
                "elapsed {elapsed}  eta {remaining}{postfix}")
#: The same below one item per second: seconds per item (``{unit}`` is then the singular,
#: "field" for "fields").
SLOW_FORMAT = ("{desc} {n_fmt}/{total_fmt} ({percentage:.1f} %)  {rate_inv:.1f} s/{unit}  "
               "elapsed {elapsed}  eta {remaining}{postfix}")


def is_terminal(stream: TextIO) -> bool:
    """True if ``stream`` is an interactive terminal (False for anything without isatty)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or already closed
        return False


def terminal_columns(stream: TextIO) -> int | None:
    """Width of the terminal ``stream`` writes to, or None when it reports no usable size
    (fewer than 20 columns or 2 lines, e.g. 0 x 0)."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, ValueError, OSError, io.UnsupportedOperation):
        return None
    return size.columns if size.columns >= 20 and size.lines >= 2 else None


class ProgressDisplay:
    """Items done of ``total``, items/s and time left, on ``stream`` (default stderr).

    Parameters
    ----------
    total : int
        Items expected (frames, fields).
    desc : str, keyword-only
        What is counted, the first word of the line (``"frames"``, ``"fields"``).
    stream : text stream, keyword-only
        Where to write; default ``sys.stderr`` at construction.
    every_s : float, keyword-only
        Seconds between plain lines when ``stream`` is not a terminal.
    terminal : bool, keyword-only
        Force the bar (True) or the plain lines (False); default ``stream.isatty()``.
    """

    def __init__(self, total: int, *, desc: str = "frames", stream: TextIO | None = None,
                 every_s: float = 5.0, terminal: bool | None = None) -> None:
        self.total = int(total)
        self.desc = desc
        self.stream: TextIO | None = stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream) if terminal is None else terminal
        self.every_s = every_s
        self._last = -every_s  # the first plain line comes at once
        self.lines = 0  # plain lines written
        self._bar: tqdm | None = None  # type: ignore[type-arg]
        if self.tty:
            known = terminal_columns(self.stream) is not None
            # a terminal that reports no size (0 x 0: some pseudo-terminals) gets 100 x 20:
            # tqdm would draw nothing in a width or height of 0
            self._bar = tqdm(total=self.total, desc=self.desc, unit=self.desc,
                             file=self.stream, dynamic_ncols=known,
                             ncols=None if known else 100, nrows=None if known else 20,
                             leave=True)

    def update(self, done: int, elapsed: float, *, note: str = "") -> None:
        """Report ``done`` items after ``elapsed`` seconds; ``note`` is appended."""
        if self.stream is None:
            return
        try:
            if self._bar is not None:
                self._bar.set_postfix_str(note, refresh=False)
                self._bar.update(done - self._bar.n)
                return
            if elapsed - self._last < self.every_s:
                return
            self._last = elapsed
            rate = done / elapsed if elapsed > 0 else 0.0
            slow = 0.0 < rate < 1.0
            unit = self.desc.removesuffix("s") if slow else self.desc
            line = tqdm.format_meter(done, self.total, elapsed, unit=unit,
                                     prefix=self.desc, postfix=note or None, rate=rate,
                                     bar_format=SLOW_FORMAT if slow else PLAIN_FORMAT)
            self.stream.write(line + "\n")
            self.stream.flush()
            self.lines += 1
        except (OSError, ValueError):  # a closed terminal or pipe must not stop the work
            self._off()

    def close(self) -> None:
        """End the display (the bar's line is finished with a newline)."""
        if self._bar is not None:
            try:
                self._bar.close()
            except (OSError, ValueError):
                pass
            self._bar = None
        self.stream = None

    def _off(self) -> None:
        if self._bar is not None:
            self._bar.disable = True  # tqdm writes nothing more, not even at close
        self._bar = None
        self.stream = None

    def __enter__(self) -> ProgressDisplay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ScanProgress(ProgressDisplay):
    """The pipeline's progress hook (:class:`sffscan.pipeline.runtime.Pipeline`'s
    ``on_progress``): frames through the last stage before the mosaic, of the planned
    frame count, and the frames acquired so far."""

    def __init__(self, total: int, *, stream: TextIO | None = None, every_s: float = 5.0,
                 terminal: bool | None = None) -> None:
        super().__init__(total, desc="frames", stream=stream, every_s=every_s,
                         terminal=terminal)

    _stats: list[StageStats] | None = None
    _t0 = 0.0

    def __call__(self, stats: list[StageStats], elapsed: float) -> None:
        self._stats, self._t0 = stats, time.perf_counter() - elapsed
        # frames through the last stage before the mosaic that counts frames: a stage
        # after the depth stage (the calibration's correction) counts depth blocks
        done = next((s.frames for s in reversed(stats[:-1]) if s.unit == "frames"),
                    stats[0].frames)
        self.update(done, elapsed, note=f"acquired {stats[0].frames}")

    def close(self) -> None:
        """Show the final counts (the pipeline's statistics are live objects), then end."""
        if self._stats is not None and self.stream is not None:
            self._last = -math.inf  # a last plain line, however soon after the previous one
            self(self._stats, time.perf_counter() - self._t0)
        super().close()
