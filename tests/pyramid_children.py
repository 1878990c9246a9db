"""Child processes of tests/pipeline/mosaic/test_mosaic_pyramid.py: a replay through the Python
API that
dies by SIGKILL around mosaic write number ``kill_at`` (kept free of pytest so that the
fork-server children start fast)."""

from __future__ import annotations

import os
import signal
from typing import Any


def torn_replay(recording: str, output: str, kill_at: int, where: str) -> None:
    """Replay ``recording`` into ``output``; the process dies

    - ``where="level0"``: during write ``kill_at``, after two of the four level-0 arrays are
      written (no pyramid write-back);
    - ``where="pyramid"``: during write ``kill_at``, after level 0 and half of the pyramid
      chunks that write writes back."""
    import numpy as np
    from sffscan.pipeline.mosaic import writer as mosaic

    from sffscan.api import replay

    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    blend, write_many = mosaic.MosaicWriter._blend, mosaic.write_many
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

    def torn_write_many(items: list[Any], **kw: Any) -> None:
        if where == "pyramid" and state.get("write") == kill_at:
            level0 = len(mosaic.ARRAYS)  # the first items: level 0, then the write-back
            write_many(items[:level0 + (len(items) - level0) // 2], **kw)
            os.kill(os.getpid(), signal.SIGKILL)
        write_many(items, **kw)

    mosaic.LAG_S = float("inf")  # what the writer holds back does not depend on the clock
    mosaic.MosaicWriter._blend = torn_blend  # type: ignore[method-assign]
    mosaic.write_many = torn_write_many  # type: ignore[assignment]
    replay(recording, output=output)
    raise SystemExit(0)
