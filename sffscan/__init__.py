"""sffscan: shape-from-focus in continuous motion.

The public Python API. Everything named in :data:`__all__` is supported; every other name
(including the modules under ``sffscan.pipeline`` and ``sffscan.stages``) is internal and
may change between releases. Nothing heavy is imported here: torch, OpenCV and zarr load
with the first call that needs them.

>>> import sffscan
>>> cfg = sffscan.demo_config()                       # doctest: +SKIP
>>> report = sffscan.scan(cfg, output="plate.zarr")   # doctest: +SKIP
>>> mosaic = sffscan.open_mosaic("plate.zarr")        # doctest: +SKIP
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from sffscan.api import (
    focus_measure,
    open_mosaic,
    reconstruct_stack,
    replay,
    scan,
)
from sffscan.pipeline.config import (
    ConfigError,
    MotionConfig,
    OpticsConfig,
    OutputConfig,
    ProcessingConfig,
    ScanConfig,
    SourceConfig,
    demo_config,
    load_config,
)
from sffscan.pipeline.messages import (
    DepthBlock,
    DepthBlockHeader,
    FocusFrame,
    Frame,
    FrameHeader,
    MosaicAttrs,
    PlacedFrame,
)

try:
    __version__ = version("sffscan")
except PackageNotFoundError:  # pragma: no cover - running from a source tree, not installed
    __version__ = "0+unknown"

__all__ = [
    "ConfigError",
    "DepthBlock",
    "DepthBlockHeader",
    "FocusFrame",
    "Frame",
    "FrameHeader",
    "MosaicAttrs",
    "MotionConfig",
    "OpticsConfig",
    "OutputConfig",
    "PlacedFrame",
    "ProcessingConfig",
    "ScanConfig",
    "SourceConfig",
    "__version__",
    "demo_config",
    "focus_measure",
    "load_config",
    "open_mosaic",
    "reconstruct_stack",
    "replay",
    "scan",
]
