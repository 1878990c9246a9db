"""Band workers in a whole scan (issue 28): ``processing.workers`` and ``processing.bands``
(threads or band processes) change how the focus measure and the depth stage split each
frame, never the mosaic."""

from __future__ import annotations

import re
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
