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

import typing as _typing
from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _version
from pathlib import Path as _Path

# Imported from a source tree (the clone's folder on sys.path: ``python -m pytest`` or a
# script run in the clone): the sub-packages are the clone's top-level folders pipeline/,
# stages/ and schemas/, which an installed sffscan holds inside this folder (pyproject's
# package-dir mapping), so they are looked for there too.
_HERE = _Path(__file__).parent
if not (_HERE / "pipeline").is_dir() and (_HERE.parent / "pipeline" / "__init__.py").is_file():
    __path__.append(str(_HERE.parent))

from sffscan.api import (  # noqa: E402 (after the source tree's path)
    focus_measure,
    open_mosaic,
    reconstruct_stack,
    replay,
    scan,
)
from sffscan.pipeline.config import (  # noqa: E402 (after the source tree's path)
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
from sffscan.pipeline.messages import (  # noqa: E402 (after the source tree's path)
    DepthBlock,
    DepthBlockHeader,
    FocusFrame,
    Frame,
    FrameHeader,
    MosaicAttrs,
    PlacedFrame,
)

if _typing.TYPE_CHECKING:
    from sffscan.pipeline.batch import BatchError, BatchRow, find_recordings, run_batch
    from sffscan.pipeline.formats.exports import MosaicRegion, read_region, write_ply, write_x3p
    from sffscan.pipeline.formats.recording import RecordingError
    from sffscan.pipeline.metrology.areal import ArealParameters, areal_parameters
    from sffscan.pipeline.runtime import StageFailed
    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.fields.stationary import FieldResult, StackSettings

try:
    __version__ = _version("sffscan")
except _PackageNotFoundError:  # pragma: no cover - running from a source tree, not installed
    __version__ = "0+unknown"

#: Names of the API whose modules load zarr, OpenCV or torch: imported on first use.
_LAZY = {
    "ArealParameters": "sffscan.pipeline.metrology.areal",
    "BatchError": "sffscan.pipeline.batch",
    "BatchRow": "sffscan.pipeline.batch",
    "FieldResult": "sffscan.stages.fields.stationary",
    "MosaicRegion": "sffscan.pipeline.formats.exports",
    "areal_parameters": "sffscan.pipeline.metrology.areal",
    "find_recordings": "sffscan.pipeline.batch",
    "read_region": "sffscan.pipeline.formats.exports",
    "run_batch": "sffscan.pipeline.batch",
    "write_ply": "sffscan.pipeline.formats.exports",
    "write_x3p": "sffscan.pipeline.formats.exports",
    "RecordingError": "sffscan.pipeline.formats.recording",
    "ScanReport": "sffscan.pipeline.wiring",
    "StackSettings": "sffscan.stages.fields.stationary",
    "StageFailed": "sffscan.pipeline.runtime",
    "open_job": "sffscan.pipeline.printjob.layer",
}


def __getattr__(name: str) -> _typing.Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'sffscan' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__all__ = [
    "ArealParameters",
    "BatchError",
    "BatchRow",
    "ConfigError",
    "DepthBlock",
    "DepthBlockHeader",
    "FieldResult",
    "FocusFrame",
    "Frame",
    "FrameHeader",
    "MosaicAttrs",
    "MosaicRegion",
    "MotionConfig",
    "OpticsConfig",
    "OutputConfig",
    "PlacedFrame",
    "ProcessingConfig",
    "RecordingError",
    "ScanConfig",
    "ScanReport",
    "SourceConfig",
    "StackSettings",
    "StageFailed",
    "__version__",
    "areal_parameters",
    "demo_config",
    "find_recordings",
    "focus_measure",
    "load_config",
    "open_job",
    "open_mosaic",
    "read_region",
    "reconstruct_stack",
    "replay",
    "run_batch",
    "scan",
    "write_ply",
    "write_x3p",
]
