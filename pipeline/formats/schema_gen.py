"""JSON Schemas in ``schemas/``, generated from the typed models (the single source of truth).

``sffscan schemas`` writes them; ``sffscan schemas --check`` (and a test) fails when a
committed file differs from what the models generate. Without ``--dir`` both work on the
packaged copy (:func:`packaged_schema_dir`: the ``sffscan.schemas`` package, i.e. the
checkout's ``schemas/`` folder in an editable install), whatever the current folder.
"""

from __future__ import annotations

import importlib.resources
import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.formats.recording import RecordingAttrs
from sffscan.pipeline.formats.transport import TransportMessage
from sffscan.pipeline.metrology.calibration_model import Calibration
from sffscan.pipeline.metrology.compare import CompareReport
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.stages.messages import DepthBlockHeader, FrameHeader

SCHEMAS: dict[str, type[BaseModel]] = {
    "frame_header.v1.json": FrameHeader,
    "depth_block_header.v1.json": DepthBlockHeader,
    "scan_config.v1.json": ScanConfig,
    "mosaic_attrs.v1.json": MosaicAttrs,
    "calibration.v1.json": Calibration,
    "recording_attrs.v1.json": RecordingAttrs,
    "transport_message.v1.json": TransportMessage,
    "compare_report.v1.json": CompareReport,
}


def packaged_schema_dir() -> Path:
    """The folder of the installed ``sffscan.schemas`` package (its JSON files)."""
    return Path(str(importlib.resources.files("sffscan.schemas")))


def schema_text(model: type[BaseModel], filename: str) -> str:
    schema: dict[str, Any] = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://sffscan.example/schemas/{filename}",
        **model.model_json_schema(),
    }
    return json.dumps(schema, indent=2, ensure_ascii=False, sort_keys=True) + "\n"


def write_schemas(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name, model in SCHEMAS.items():
        path = folder / name
        path.write_text(schema_text(model, name), encoding="utf-8")
        out.append(path)
    return out


def check_schemas(folder: Path) -> list[str]:
    """Names of schema files that are missing or differ from the models."""
    stale = []
    for name, model in SCHEMAS.items():
        path = folder / name
        if not path.is_file() or path.read_text(encoding="utf-8") != schema_text(model, name):
            stale.append(name)
    return stale
