"""The command line's one logging handler.

Every module logs through ``logging.getLogger(__name__)`` (all below the ``sffscan``
logger); the library itself configures nothing, so a program that imports sffscan routes
or silences the messages as it likes (Python's default shows warnings on stderr).
``sffscan`` (:func:`sffscan.pipeline.cli.main.main`) installs one handler on the
``sffscan`` logger for the duration of a command (:func:`cli_logging`):

- level INFO by default (status lines and warnings), WARNING with ``-q`` (warnings and
  errors only), DEBUG with ``-v`` (everything, each line with its logger's name);
- lines go to ``sys.stderr`` as it is when the line is written (so a redirected stderr
  gets them), through ``tqdm.write`` so that a progress bar on the terminal is cleared
  first and redrawn below the line;
- a status line is written as it is, a warning as ``sffscan: WARNING: ...``.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

from tqdm import tqdm

__all__ = ["LOGGER", "StderrHandler", "cli_logging", "level_for"]

LOGGER = "sffscan"


def level_for(*, quiet: bool, verbose: int) -> int:
    """The logging level of ``-q`` / ``-v`` (``-v`` wins)."""
    if verbose:
        return logging.DEBUG
    return logging.WARNING if quiet else logging.INFO


class _Formatter(logging.Formatter):
    def __init__(self, *, names: bool) -> None:
        super().__init__()
        self.names = names

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.exc_info:
            msg += "\n" + self.formatException(record.exc_info)
        if record.levelno >= logging.WARNING:
            msg = f"sffscan: {record.levelname}: {msg}"
        if self.names:
            msg = f"[{record.name}] {msg}"
        return msg


class StderrHandler(logging.Handler):
    """Writes each record to the current ``sys.stderr`` (looked up per record), around any
    tqdm bar on it."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except BrokenPipeError:
            raise  # the command's own handling ends it quietly
        except Exception:  # noqa: BLE001 - logging's own policy for a failing handler
            self.handleError(record)


@contextlib.contextmanager
def cli_logging(level: int) -> Iterator[logging.Handler]:
    """Install the command line's handler on the ``sffscan`` logger at ``level``; remove it
    (and restore the logger's level) on exit."""
    logger = logging.getLogger(LOGGER)
    handler = StderrHandler(level=logging.DEBUG)
    handler.setFormatter(_Formatter(names=level <= logging.DEBUG))
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
