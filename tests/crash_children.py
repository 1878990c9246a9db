"""Child processes of tests/pipeline/test_crash.py: the command line, run in a fork-server child so
that it can be killed (kept free of pytest so that the children start fast)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ScanConfig

from tests.scan_helpers import load_frames, rendered_scanner


def quiet_main(argv: list[str], rendered: tuple[ScanConfig, Path] | None = None) -> None:
    """``sffscan ARGV`` with stdout and stderr discarded; with ``rendered = (cfg, folder)``,
    the simulated scanner feeds the frames saved in ``folder`` (``save_frames``: all of
    ``simulate_frames(cfg)``, rendered once by the test) when the scan's configuration is
    ``cfg``, instead of rendering them again."""
    if rendered is not None:
        from sffscan.pipeline import sim_source as scanner

        cfg, folder = rendered
        scanner.simulate_frames = rendered_scanner(  # type: ignore[assignment]
            cfg, load_frames(folder))
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    raise SystemExit(main(argv))


def torn_replay(argv: list[str], kill_at: int) -> None:
    """``sffscan ARGV`` (a replay) that dies by SIGKILL in the middle of mosaic write number
    ``kill_at``: after two of the four arrays of its band are written."""
    from sffscan.pipeline.mosaic import writer as mosaic

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
