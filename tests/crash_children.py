"""Child processes of tests/test_crash.py: the command line, run in a fork-server child so
that it can be killed (kept free of pytest so that the children start fast)."""

from __future__ import annotations

import os
import signal

import numpy as np
from sffscan.pipeline.cli.main import main


def quiet_main(argv: list[str]) -> None:
    """``sffscan ARGV`` with stdout and stderr discarded."""
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    raise SystemExit(main(argv))


def torn_replay(argv: list[str], kill_at: int) -> None:
    """``sffscan ARGV`` (a replay) that dies by SIGKILL in the middle of mosaic write number
    ``kill_at``: after two of the four arrays of its band are written."""
    from sffscan.stages import mosaic

    orig = mosaic.MosaicWriter._blend

    def torn(self: mosaic.MosaicWriter, x0: int, y0: int, new: dict[str, np.ndarray]) -> None:
        if self.writes - 1 == kill_at:
            r0, c0 = y0 - self.origin[1], x0 - self.origin[0]
            rows, cols = new["weight"].shape
            sel = (slice(r0, r0 + rows), slice(c0, c0 + cols))
            arrays = {n: mosaic.mosaic_array(self.group, n) for n in mosaic.ARRAYS}
            old = {n: np.asarray(a[sel]) for n, a in arrays.items()}
            out = mosaic.blend(old, new)
            arrays["height"][sel] = out["height"]
            arrays["texture"][sel] = out["texture"]
            os.kill(os.getpid(), signal.SIGKILL)
        orig(self, x0, y0, new)

    mosaic.MosaicWriter._blend = torn  # type: ignore[method-assign]
    quiet_main(argv)
