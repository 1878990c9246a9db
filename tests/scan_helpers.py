"""Small simulated scans shared by the end-to-end tests.

The test optics keep the thesis geometry at half the resolution: 640 x 256 px of 17 µm
(FOV 10.9 x 4.4 mm), 150 fps, N = 50 levels of 200 µm, 15 mm/s, and register at half of
that resolution, i.e. on images of the same 34 µm pixels as the default optics at a
quarter; so a scan of a 20 mm strip takes about 250 frames and a few seconds on 2 cores.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.config import ScanConfig, config_from_dict
from sffscan.pipeline.metrology.evaluate import Accuracy, accuracy
from sffscan.pipeline.plan import plan_frames
from sffscan.pipeline.sim_source import make_optics, make_world, simulate_frames
from sffscan.pipeline.wiring import ScanReport, run_scan
from sffscan.stages.depth import depth_from_focus, levels_to_height
from sffscan.stages.focus_measure import focus_measure, to_unit_float
from sffscan.stages.messages import Frame, FrameHeader
from sffscan.stages.sim.camera import render_stack

SMALL: dict[str, dict[str, Any]] = {
    "source": {"world": "plate", "plate_length_mm": 24.0, "plate_width_mm": 4.0},
    "optics": {"width_px": 640, "height_px": 256, "pixel_um": 17.0},
    "motion": {"x_start_mm": 2.0, "x_end_mm": 22.0},
    "processing": {"block_columns": 64, "registration_scale": 2},
    "output": {"chunk_px": 128},
}


def small_config(**sections: dict[str, Any]) -> ScanConfig:
    data: dict[str, dict[str, Any]] = {k: dict(v) for k, v in SMALL.items()}
    for name, table in sections.items():
        data.setdefault(name, {}).update(table)
    return config_from_dict(data, origin="test")


def scan(cfg: ScanConfig, out: Path, **options: Any) -> ScanReport:
    """``run_scan`` of ``cfg``'s simulated scan (:func:`session_frames`) to ``out``;
    ``options``: more of ``run_scan``'s (``sinks``)."""
    return run_scan(cfg, frames=session_frames(cfg), output=out, progress=False, **options)


def replay(frames: Sequence[Frame]) -> Iterator[Frame]:
    """``frames`` (rendered once by a test) fed again, each image a fresh copy: a stage may
    keep or alter the array it gets, and no other run must see that."""
    for f in frames:
        yield Frame(f.header, np.array(f.image))  # a plain ndarray, also of a memmap


class FrameCache:
    """Simulated scans, each rendered once per test session, shared by pytest-xdist's workers.

    ``frames(cfg)`` is all of ``simulate_frames(cfg)``: the first worker to ask renders the
    scan and saves it under ``root`` (:func:`save_frames`, under a file lock: a worker asking
    for a scan another is rendering waits for it instead of rendering it too); every later
    request, in any worker, reads it back memory-mapped. Scans are keyed by all that
    ``simulate_frames`` reads: the world (``source``), the ``optics``, the ``motion`` and the
    scan plan itself (every frame's position, focus level, pass, timestamp); so configurations
    that differ only in processing or output (registration on or off, a calibration, the
    mosaic's path) share one rendering. ``root`` belongs to one test session (conftest's
    ``frame_cache``): nothing rendered by an older version of the code is ever read.
    """

    def __init__(self, root: Path) -> None:
        self.root = root

    @staticmethod
    def key(cfg: ScanConfig) -> str:
        h = hashlib.sha256()
        for part in (cfg.source, cfg.optics, cfg.motion):
            h.update(part.model_dump_json().encode())
        h.update(repr(list(plan_frames(cfg))).encode())
        return h.hexdigest()[:24]

    def folder(self, cfg: ScanConfig) -> Path:
        """The folder of ``cfg``'s frames (:func:`save_frames`), rendered if no one has yet."""
        self.root.mkdir(parents=True, exist_ok=True)
        key = self.key(cfg)
        done = self.root / key
        with open(self.root / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the holder ends, even killed
            if not done.is_dir():
                part = self.root / f"{key}.{os.getpid()}.part"
                shutil.rmtree(part, ignore_errors=True)
                save_frames(list(simulate_frames(cfg)), part)
                part.rename(done)
        return done

    def frames(self, cfg: ScanConfig) -> list[Frame]:
        """All of ``simulate_frames(cfg)``, images memory-mapped read-only: feed them to a
        run through :func:`replay` (fresh, writable copies)."""
        return load_frames(self.folder(cfg))


#: the environment variable naming the session's cache folder (tests/conftest.py sets it)
FRAME_CACHE_ENV = "SFFSCAN_TEST_FRAME_CACHE"


def session_cache() -> FrameCache | None:
    """The test session's :class:`FrameCache` (conftest's ``frame_cache`` names its folder
    in ``$SFFSCAN_TEST_FRAME_CACHE``); ``None`` outside a test session."""
    root = os.environ.get(FRAME_CACHE_ENV)
    return FrameCache(Path(root)) if root else None


def session_frames(cfg: ScanConfig) -> Iterator[Frame]:
    """``simulate_frames(cfg)``: from the session's :class:`FrameCache` where there is one
    (fresh copies of frames rendered once), else rendered now."""
    cache = session_cache()
    return replay(cache.frames(cfg)) if cache is not None else simulate_frames(cfg)


def session_scanner(cfg: ScanConfig, *, world: Any = None) -> Iterator[Frame]:
    """A stand-in for ``sffscan.pipeline.sim_source.simulate_frames`` that reads the session's
    cache (:func:`session_frames`): set it on that module and the command line's simulated
    source (``pipeline.sources.open_feed``) feeds the frames of a scan rendered once for the
    session. ``world`` is ignored: the pipeline passes ``make_world(cfg)``, the world the
    cache's rendering uses too."""
    return session_frames(cfg)


class RenderedScan:
    """``simulate_frames(cfg)``, each frame rendered once, however many times it is read.

    Iterating yields the scan's frames from the first (as :func:`replay` does: fresh copies).
    With the session's :class:`FrameCache` (the test runs), the frames are those of the cache,
    rendered once for the whole session; without one, they are rendered lazily, only those no
    earlier iteration reached. Tests that feed the same scan to several runs (bad-input
    variants, with and without positions) render it once.
    """

    def __init__(self, cfg: ScanConfig) -> None:
        self.cfg = cfg
        cache = session_cache()
        self._cached = cache.frames(cfg) if cache is not None else None
        self._source = simulate_frames(cfg)
        self._frames: list[Frame] = []

    def __iter__(self) -> Iterator[Frame]:
        if self._cached is not None:
            yield from replay(self._cached)
            return
        i = 0
        while True:
            if i == len(self._frames):
                f = next(self._source, None)
                if f is None:
                    return
                self._frames.append(f)
            yield Frame(self._frames[i].header, self._frames[i].image.copy())
            i += 1


def save_frames(frames: Sequence[Frame], folder: Path) -> Path:
    """``frames`` to ``folder`` (images.npy, headers.json) for :func:`load_frames` in a child
    process: read from the page cache, not pickled through a pipe."""
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "images.npy", np.stack([f.image for f in frames]))
    (folder / "headers.json").write_text(
        "[" + ",".join(f.header.model_dump_json() for f in frames) + "]", encoding="utf-8")
    return folder


def load_frames(folder: Path) -> list[Frame]:
    """The frames :func:`save_frames` wrote (images memory-mapped, read-only)."""
    import json

    images = np.load(folder / "images.npy", mmap_mode="r")
    headers = json.loads((folder / "headers.json").read_text(encoding="utf-8"))
    return [Frame(FrameHeader.model_validate(h), images[i]) for i, h in enumerate(headers)]


def rendered_scanner(cfg: ScanConfig, frames: Sequence[Frame]
                     ) -> Callable[..., Iterator[Frame]]:
    """A stand-in for ``sffscan.pipeline.sim_source.simulate_frames`` that replays ``frames`` (the
    whole of ``simulate_frames(cfg)``, rendered once) for ``cfg`` and renders any other
    configuration as before: set it on the scanner module and the command line's simulated
    source (``pipeline.sources.open_feed``) feeds the same frames without rendering them.
    Rendering is not what the crash tests test, and it was about half of their scans' CPU
    (the 115-frame scan of tests/pipeline/test_crash.py: 2.4-3.0 s CPU rendered, 1.1 s replayed,
    interleaved runs on the shared 2-core VM)."""
    from sffscan.pipeline import sim_source as scanner

    render = scanner.simulate_frames

    def simulate_frames(c: ScanConfig, *, world: Any = None) -> Iterator[Frame]:
        # the same scan but for where its output goes (the command line's ``-o``)
        same = c.model_copy(update={"output": cfg.output}) == cfg
        return replay(frames) if same else render(c, world=world)

    return simulate_frames


def max_depth(cfg: ScanConfig) -> float:
    return (cfg.optics.n_levels - 1) * cfg.optics.z_step_um


def strip_region(cfg: ScanConfig) -> tuple[int, int, int, int]:
    """World px box of the strip that a single pass must cover completely.

    Columns: [x_start, x_end]. Rows: the frame's rows inside the planning margin (one row
    more than the focus volume needs), less the across-motion wobble amplitude: a row must
    be seen at all N levels.
    """
    o, m = cfg.optics, cfg.motion
    px = o.pixel_um / 1000.0
    inset = cfg.processing.edge_margin_px + int(np.ceil(m.wobble_across_px))
    y = int(round(m.y_start_mm / px))
    return (int(np.ceil(m.x_start_mm / px)), y + inset, int(np.floor(m.x_end_mm / px)),
            y + o.height_px - inset)


def mosaic_height(path: Path, region: tuple[int, int, int, int], *,
                  array: str = "height") -> np.ndarray:
    """The mosaic's height (or another ``array``) over a world px box (NaN where the mosaic
    has nothing)."""
    g = zarr.open_group(str(path), mode="r")
    ox, oy = (int(v) for v in g.attrs["origin_px"])  # type: ignore[union-attr,arg-type]
    x0, y0, x1, y1 = region
    return np.asarray(g[array][y0 - oy:y1 - oy, x0 - ox:x1 - ox])  # type: ignore[index]


def truth(cfg: ScanConfig, region: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = region
    return make_world(cfg).height_um(float(x0), float(y0), x1 - x0, y1 - y0)


def score(cfg: ScanConfig, est: np.ndarray, region: tuple[int, int, int, int],
          mask: np.ndarray | None = None) -> Accuracy:
    return accuracy(est, truth(cfg, region), max_depth=max_depth(cfg), mask=mask)


def stationary_height(cfg: ScanConfig, region: tuple[int, int, int, int]) -> np.ndarray:
    """Stop-and-go reference: stationary stacks of fields tiling ``region``, same processing.

    Each field is the camera standing still over the surface, one frame per focus level
    (the same optics, noise and operators as the scan). Only each field's interior (the
    focus-window margin and the median halo excluded) is kept, and the fields are placed so
    that their interiors tile the region's columns; rows outside one field's interior stay
    NaN.
    """
    o, p = cfg.optics, cfg.processing
    world = make_world(cfg)
    optics = make_optics(cfg)
    rng = np.random.default_rng(cfg.source.seed + 7)
    heights = np.asarray(o.focus_heights_um())
    m = p.edge_margin_px + p.median_size
    x0, y0, x1, y1 = region
    step = o.width_px - 2 * m
    h = min(o.height_px - 2 * m, y1 - y0)
    fy = y0 + (y1 - y0 - h) // 2 - m
    est = np.full((y1 - y0, x1 - x0), np.nan, np.float32)
    for fx in range(x0 - m, x1 - m, step):
        stack = render_stack(world, x0=float(fx), y0=float(fy), focus_heights_um=heights,
                             optics=optics, rng=rng)
        vol = np.stack([focus_measure(to_unit_float(img, max_value=o.max_value),
                                      operator=p.focus_operator, window=p.window)
                        for img in stack])
        depth, _ = depth_from_focus(vol, method=p.depth_method, median_size=p.median_size,
                                    spread_size=p.window)
        height = levels_to_height(depth, focus_heights_um=heights)
        w = min(step, x1 - fx - m)
        r = fy + m - y0
        est[r:r + h, fx + m - x0:fx + m - x0 + w] = height[m:m + h, m:m + w]
    return est
