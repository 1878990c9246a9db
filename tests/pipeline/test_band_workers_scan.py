"""Band workers in a whole scan (issue 28): ``processing.workers`` changes how the focus
measure and the depth stage split each frame, never the mosaic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.wiring import run_scan

from tests.scan_helpers import small_config

ARRAYS = ("height", "texture", "weight", "confidence", "uncertainty")


def test_mosaic_is_bit_identical_for_any_number_of_band_workers(tmp_path: Path) -> None:
    motion = {"x_end_mm": 6.0, "wobble_along_px": 1.0, "wobble_across_px": 1.0}
    frames = list(simulate_frames(small_config(motion=motion)))
    out: dict[tuple[str, int], dict[str, np.ndarray]] = {}
    for mode, k in (("threads", 1), ("threads", 3), ("processes", 2)):
        cfg = small_config(motion=motion, processing={"execution": mode, "workers": k})
        path = tmp_path / f"{mode}-{k}.zarr"
        rep = run_scan(cfg, frames=iter(frames), output=path, progress=False)
        assert rep.frames == len(frames) and rep.result.dropped == 0
        group = zarr.open_group(str(path), mode="r")
        assert group.attrs["status"] == "complete"
        out[(mode, k)] = {a: np.asarray(zarr.open_array(str(path / a), mode="r")[...])
                          for a in ARRAYS}
    ref = out[("threads", 1)]
    assert np.isfinite(ref["height"]).sum() > 1000
    for key, arrays in out.items():
        for name, a in arrays.items():
            assert a.dtype == ref[name].dtype and a.shape == ref[name].shape, (key, name)
            assert a.tobytes() == ref[name].tobytes(), (key, name)
