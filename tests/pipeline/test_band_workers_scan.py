"""Band workers in a whole scan (issue 28): ``processing.workers`` and ``processing.bands``
(threads or band processes) change how the focus measure and the depth stage split each
frame, never the mosaic."""

from __future__ import annotations

import multiprocessing as mp
import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.runtime import StageFailed
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.wiring import run_scan

from tests.scan_helpers import small_config

ARRAYS = ("height", "texture", "weight", "confidence", "uncertainty")


def test_mosaic_is_bit_identical_for_any_number_of_band_workers(tmp_path: Path) -> None:
    motion = {"x_end_mm": 6.0, "wobble_along_px": 1.0, "wobble_across_px": 1.0}
    frames = list(simulate_frames(small_config(motion=motion)))
    out: dict[tuple[str, int, str], dict[str, np.ndarray]] = {}
    for mode, k, bands in (("threads", 1, "threads"), ("threads", 3, "threads"),
                           ("processes", 2, "threads"), ("threads", 2, "processes"),
                           ("processes", 3, "processes")):
        cfg = small_config(motion=motion, processing={"execution": mode, "workers": k,
                                                      "bands": bands})
        path = tmp_path / f"{mode}-{k}-{bands}.zarr"
        rep = run_scan(cfg, frames=iter(frames), output=path, progress=False)
        assert rep.frames == len(frames) and rep.result.dropped == 0
        group = zarr.open_group(str(path), mode="r")
        assert group.attrs["status"] == "complete"
        if bands == "processes":  # its band processes measured the focus, then stopped
            assert not [p for p in Path("/dev/shm").glob("sffscan-*-band-*")
                        if re.fullmatch(r"sffscan-\d+-band-[0-9a-f]{8}", p.name)]
        out[(mode, k, bands)] = {a: np.asarray(zarr.open_array(str(path / a), mode="r")[...])
                          for a in ARRAYS}
    ref = out[("threads", 1, "threads")]
    assert np.isfinite(ref["height"]).sum() > 1000
    for key, arrays in out.items():
        for name, a in arrays.items():
            assert a.dtype == ref[name].dtype and a.shape == ref[name].shape, (key, name)
            assert a.tobytes() == ref[name].tobytes(), (key, name)


def test_a_band_process_that_dies_fails_the_depth_stage_and_keeps_the_mosaic(
        tmp_path: Path) -> None:
    """A band process killed mid-scan: the scan stops with the depth stage named and the
    helper's death as the cause, the mosaic is marked failed and keeps what was written,
    and nothing is left behind (processes, shared memory)."""
    motion = {"x_end_mm": 12.0}
    cfg = small_config(motion=motion, processing={"execution": "threads", "workers": 2,
                                                  "bands": "processes"})
    frames = list(simulate_frames(cfg))

    def killing() -> Iterator[Any]:
        for i, f in enumerate(frames):
            if i == len(frames) - 1:  # the depth stage is some frames behind
                helpers = [p for p in mp.active_children() if p.name.startswith("sffscan-band")]
                assert len(helpers) == 1
                os.kill(helpers[0].pid, signal.SIGKILL)  # reaped by the band pool
            yield f

    out = tmp_path / "killed.zarr"
    with pytest.raises(StageFailed, match=r"sffscan-band-1 \(\w+, rows \d+\.\.\d+\) died, "
                       r"exit code -9") as info:
        run_scan(cfg, frames=killing(), output=out, progress=False)
    assert info.value.stage == "depth"
    group = zarr.open_group(str(out), mode="r")
    assert group.attrs["status"] == "failed"
    assert np.isfinite(np.asarray(group["height"])).sum() > 100  # the blocks before it
    assert not [p for p in mp.active_children() if p.name.startswith("sffscan-band")]
    assert not [p for p in Path("/dev/shm").glob(f"sffscan-{os.getpid()}-band-*")]
