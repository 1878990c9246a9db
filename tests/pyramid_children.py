"""Child processes of tests/test_mosaic_pyramid.py: a replay through the Python API that
dies by SIGKILL in the middle of mosaic write number ``kill_at`` (kept free of pytest so that
the fork-server children start fast)."""

from __future__ import annotations

import os
import signal
from typing import Any


def torn_replay(recording: str, output: str, kill_at: int, where: str) -> None:
    """Replay ``recording`` into ``output``; during write ``kill_at`` the process dies:
    ``where="level0"`` after two of the four level-0 arrays are written (no pyramid update),
    ``where="pyramid"`` after level 0 and half of level 1 are written."""
    import numpy as np
    from sffscan.stages import mosaic, mosaic_pyramid

    from sffscan.api import replay

    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    blend, levels = mosaic.MosaicWriter._blend, mosaic_pyramid.write_levels
    state: dict[str, Any] = {}

    def torn_blend(self: mosaic.MosaicWriter, x0: int, y0: int,
                   new: dict[str, np.ndarray]) -> None:
        state["write"] = self.writes - 1
        if where == "level0" and self.writes - 1 == kill_at:
            r0, c0 = y0 - self.origin[1], x0 - self.origin[0]
            rows, cols = new["weight"].shape
            sel = (slice(r0, r0 + rows), slice(c0, c0 + cols))
            arrays = {n: mosaic.mosaic_array(self.group, n) for n in mosaic.ARRAYS}
            out = mosaic.blend({n: np.asarray(a[sel]) for n, a in arrays.items()}, new)
            arrays["height"][sel] = out["height"]
            arrays["texture"][sel] = out["texture"]
            os.kill(os.getpid(), signal.SIGKILL)
        blend(self, x0, y0, new)

    def torn_levels(arrays: list[dict[str, Any]], region: Any, values: Any) -> None:
        if where == "pyramid" and state.get("write") == kill_at:
            levels([{k: v for k, v in arrays[0].items() if k in ("height", "texture")}],
                   region, values)
            os.kill(os.getpid(), signal.SIGKILL)
        levels(arrays, region, values)

    mosaic.MosaicWriter._blend = torn_blend  # type: ignore[method-assign]
    mosaic.write_levels = torn_levels  # type: ignore[assignment]
    replay(recording, output=output)
    raise SystemExit(0)
