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
from pathlib import Path as _Path

# Imported from a source tree (the clone's folder on sys.path: ``python -m pytest`` or a
# script run in the clone): the sub-packages are the clone's top-level folders pipeline/,
# stages/ and schemas/, which an installed sffscan holds inside this folder (pyproject's
# package-dir mapping), so they are looked for there too.
_HERE = _Path(__file__).parent
if not (_HERE / "pipeline").is_dir() and (_HERE.parent / "pipeline" / "__init__.py").is_file():
    __path__.append(str(_HERE.parent))

if _typing.TYPE_CHECKING:
    from sffscan.api import focus_measure, open_mosaic, reconstruct_stack, replay, scan
    from sffscan.pipeline.batch import run_batch
    from sffscan.pipeline.batch_targets import BatchError, BatchRow, find_recordings
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
    from sffscan.pipeline.formats.exports import MosaicRegion, read_region, write_ply, write_x3p
    from sffscan.pipeline.formats.recording import RecordingError
    from sffscan.pipeline.metrology.areal import ArealParameters, areal_parameters
    from sffscan.pipeline.mosaic.attrs import MosaicAttrs
    from sffscan.pipeline.runtime import StageFailed
    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.fields.stationary import FieldResult, StackSettings
    from sffscan.stages.messages import (
        DepthBlock,
        DepthBlockHeader,
        FocusFrame,
        Frame,
        FrameHeader,
        PlacedFrame,
    )

    __version__: str

#: Where each name of the API lives: imported on first use, so that ``import sffscan`` (and
#: the command line's ``--help``) loads neither numpy, pydantic nor zarr.
_LAZY = {
    **dict.fromkeys(("focus_measure", "open_mosaic", "reconstruct_stack", "replay", "scan"),
                    "sffscan.api"),
    **dict.fromkeys(("ConfigError", "MotionConfig", "OpticsConfig", "OutputConfig",
                     "ProcessingConfig", "ScanConfig", "SourceConfig", "demo_config",
                     "load_config"), "sffscan.pipeline.config"),
    **dict.fromkeys(("DepthBlock", "DepthBlockHeader", "FocusFrame", "Frame", "FrameHeader",
                     "PlacedFrame"), "sffscan.stages.messages"),
    "MosaicAttrs": "sffscan.pipeline.mosaic.attrs",
    **dict.fromkeys(("ArealParameters", "areal_parameters"), "sffscan.pipeline.metrology.areal"),
    **dict.fromkeys(("BatchError", "BatchRow", "find_recordings"),
                    "sffscan.pipeline.batch_targets"),
    "run_batch": "sffscan.pipeline.batch",
    **dict.fromkeys(("MosaicRegion", "read_region", "write_ply", "write_x3p"),
                    "sffscan.pipeline.formats.exports"),
    **dict.fromkeys(("FieldResult", "StackSettings"), "sffscan.stages.fields.stationary"),
    "RecordingError": "sffscan.pipeline.formats.recording",
    "ScanReport": "sffscan.pipeline.wiring",
    "StageFailed": "sffscan.pipeline.runtime",
    "open_job": "sffscan.pipeline.printjob.layer",
}


def _distribution_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sffscan")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree, not installed
        return "0+unknown"


def __getattr__(name: str) -> _typing.Any:
    if name == "__version__":
        value: _typing.Any = _distribution_version()
    else:
        module = _LAZY.get(name)
        if module is None:
            raise AttributeError(f"module 'sffscan' has no attribute {name!r}")
        import importlib

        value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


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
