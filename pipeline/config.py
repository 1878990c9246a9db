"""Scan configuration: the file's tables, TOML loading and writing, feasibility checks.

A configuration has the tables ``[source]``, ``[optics]``, ``[motion]``, ``[processing]``,
``[output]``, ``[camera]`` and ``[daq]`` (docs/configuration.md, generated from these
models). Each table is composed of parts from :mod:`sffscan.pipeline.config_groups`, one
per group of settings: what is measured, how it runs, the simulator's own parameters
(``[optics]`` = the instrument's :class:`~sffscan.pipeline.config_groups.Optics` + the
simulated lens, :class:`~sffscan.pipeline.config_groups.SimLens`). Every error names the
field, for example ``optics.pixel_um``.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator
from sffscan.pipeline.config_groups import (
    GROUP_TITLES,
    ConfigModel,
    Execution,
    Method,
    Motion,
    Optics,
    Output,
    SimLens,
    SimMotion,
    SimWorld,
    SourceKind,
    Transport,
    group_of,
)
from sffscan.pipeline.hardware.config import CameraConfig, DaqConfig

__all__ = [
    "REALISTIC_OPTICS",
    "ConfigError",
    "MotionConfig",
    "OpticsConfig",
    "OutputConfig",
    "ProcessingConfig",
    "ScanConfig",
    "SourceConfig",
    "check_feasible",
    "config_from_dict",
    "config_to_toml",
    "demo_config",
    "load_config",
    "max_speed_sliding_mm_s",
    "max_speed_thesis_mm_s",
    "pass_pitch_px",
    "shift_per_frame_px",
    "usable_width_px",
]


class ConfigError(ValueError):
    """An invalid or impossible configuration; the message names the field."""


# The tables of the file, each composed of parts (config_groups). A table lists its parts
# last to first: pydantic orders the fields base class first, so the TOML keys follow the
# parts' order.


class SourceConfig(SimWorld, Transport, SourceKind):
    """The frame source, the network transport and the simulated world."""


class OpticsConfig(SimLens, Optics):
    """The instrument's optics and the simulated lens."""

    def magnification_reference_um(self) -> float:
        """Focus height where the simulated magnification is 1, µm."""
        if self.magnification_ref_um is not None:
            return self.magnification_ref_um
        return self.z_min_um + 0.5 * (self.n_levels - 1) * self.z_step_um


class MotionConfig(SimMotion, Motion):
    """The stage's travel and the simulated stage's wobble."""


class ProcessingConfig(Execution, Method):
    """The measuring method, and where and how the stages compute."""

    @model_validator(mode="after")
    def _band_processes_measure_with_opencv(self) -> ProcessingConfig:
        if self.bands == "processes" and self.backend != "opencv":
            raise ValueError(f"bands = 'processes' measures the focus with the OpenCV "
                             f"backend; backend is {self.backend!r}")
        return self


class OutputConfig(Output):
    """The Zarr store of the height mosaic."""


class ScanConfig(ConfigModel):
    """A scan: what is measured, how it runs, and the simulator's parameters."""

    version: Literal[1] = Field(1, description="Configuration format version")
    source: SourceConfig = Field(default_factory=lambda: SourceConfig())
    optics: OpticsConfig = Field(default_factory=lambda: OpticsConfig())
    motion: MotionConfig = Field(default_factory=lambda: MotionConfig())
    processing: ProcessingConfig = Field(default_factory=lambda: ProcessingConfig())
    output: OutputConfig = Field(default_factory=lambda: OutputConfig())
    camera: CameraConfig = Field(default_factory=lambda: CameraConfig())
    daq: DaqConfig = Field(default_factory=lambda: DaqConfig())


# --- derived quantities -------------------------------------------------------------------


def shift_per_frame_px(cfg: ScanConfig) -> float:
    """Stage travel between two frames, px: speed / (fps * pixel scale)."""
    return cfg.motion.speed_mm_s * 1000.0 / (cfg.optics.fps * cfg.optics.pixel_um)


def usable_width_px(cfg: ScanConfig) -> float:
    """Frame width along the motion that enters the focus volume, px.

    The focus-measure margin is excluded at both edges, and so are the along-motion wobble
    amplitude and one pixel of rounding, since positions are integer.
    """
    return (cfg.optics.width_px - 2 * cfg.processing.edge_margin_px
            - 2 * (cfg.motion.wobble_along_px + 1.0))


def max_speed_sliding_mm_s(cfg: ScanConfig) -> float:
    """Largest speed at which every world column is seen at all N levels, mm/s.

    A column stays inside the usable width for at least floor(usable / shift) consecutive
    frames, and N consecutive frames hold every focus level once, so shift <= usable / N.
    """
    o = cfg.optics
    return usable_width_px(cfg) / o.n_levels * o.fps * o.pixel_um / 1000.0


def max_speed_thesis_mm_s(cfg: ScanConfig, *, overlap: float = 0.0) -> float:
    """The thesis' per-stack limit s = (r / N) * l with l = (w - w P) / 2 (eq. 6.1-6.3), mm/s."""
    o = cfg.optics
    w_mm = o.width_px * o.pixel_um / 1000.0
    return o.fps / o.n_levels * (w_mm - w_mm * overlap) / 2.0


def pass_pitch_px(cfg: ScanConfig) -> float:
    """Distance between adjacent passes along y, px."""
    usable_h = cfg.optics.height_px - 2 * cfg.processing.edge_margin_px
    return usable_h * (1.0 - cfg.motion.pass_overlap)


def check_feasible(cfg: ScanConfig) -> None:
    """Raise :class:`ConfigError` for a configuration that cannot measure its strip."""
    p, o = cfg.processing, cfg.optics
    for name, size in (("window", p.window), ("median_size", p.median_size)):
        if size > min(o.width_px, o.height_px) // 2:
            raise ConfigError(
                f"processing.{name} = {size} px is more than half the frame "
                f"({o.width_px} x {o.height_px} px, optics.width_px x optics.height_px)")
    if usable_width_px(cfg) < cfg.optics.n_levels:
        raise ConfigError(
            f"optics.width_px = {cfg.optics.width_px} px leaves {usable_width_px(cfg):.0f} px "
            f"after margins and wobble: fewer than optics.n_levels = {cfg.optics.n_levels}"
        )
    vmax = max_speed_sliding_mm_s(cfg)
    if cfg.motion.speed_mm_s > vmax:
        raise ConfigError(
            f"motion.speed_mm_s = {cfg.motion.speed_mm_s:g} mm/s exceeds the limit "
            f"{vmax:.2f} mm/s at which every column is still seen at all {cfg.optics.n_levels} "
            f"focus levels ({cfg.optics.fps:g} fps, {cfg.optics.width_px} px x "
            f"{cfg.optics.pixel_um:g} µm/px)"
        )
    if cfg.motion.x_end_mm <= cfg.motion.x_start_mm:
        raise ConfigError(
            f"motion.x_end_mm = {cfg.motion.x_end_mm:g} must be greater than "
            f"motion.x_start_mm = {cfg.motion.x_start_mm:g}"
        )
    if cfg.processing.median_size > cfg.optics.height_px:
        raise ConfigError("processing.median_size is larger than optics.height_px")
    if not math.isfinite(cfg.optics.z_min_um):
        raise ConfigError("optics.z_min_um must be finite")


# --- loading ------------------------------------------------------------------------------


def _format_validation(err: ValidationError, origin: str) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        got = f" (got {e['input']!r})" if "input" in e and not isinstance(e["input"], dict) else ""
        msg = e["msg"].removeprefix("Value error, ")  # a validator's own message, as is
        if got and f"got {e['input']!r}" in msg:  # the validator's message names it
            got = ""
        lines.append(f"{origin}: {loc}: {msg}{got}")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any], *, origin: str = "configuration") -> ScanConfig:
    """Validate a nested dict into a :class:`ScanConfig`, then check feasibility."""
    try:
        cfg = ScanConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation(err, origin)) from None
    check_feasible(cfg)
    return cfg


def load_config(path: str | Path) -> ScanConfig:
    """Read a TOML scan configuration; errors name the file and the field."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{p}: not UTF-8 text (byte {err.start}); TOML files are UTF-8"
                          ) from None
    except OSError as err:
        raise ConfigError(f"{p}: cannot read the configuration: {err.strerror}") from None
    return config_from_dict(data, origin=str(p))


REALISTIC_OPTICS: dict[str, float] = {
    "magnification_per_mm": 0.002,  # +2 % magnification over the demo's 9.8 mm focus range
    "field_curvature_um": 150.0,  # best focus 150 µm higher at the frame corner
    "vignetting": 0.2,  # 20 % less light at the frame corner
}
"""``[optics]`` values of a real non-telecentric tunable-lens objective (``demo --realistic``)."""


def demo_config(*, passes: int = 1, **sections: dict[str, Any]) -> ScanConfig:
    """The built-in simulated scan: the characterisation plate at 15 mm/s (thesis optics)."""
    data: dict[str, Any] = {
        "source": {"kind": "sim", "world": "plate", "plate_length_mm": 40.0,
                   "plate_width_mm": 8.0 * passes},
        "motion": {"x_start_mm": 0.0, "x_end_mm": 40.0, "passes": passes},
    }
    for name, table in sections.items():
        data.setdefault(name, {}).update(table)
    return config_from_dict(data, origin="demo")


def config_to_toml(cfg: ScanConfig) -> str:
    """Render a configuration as TOML (the inverse of :func:`load_config`)."""
    out: list[str] = [f"version = {cfg.version}", ""]
    for name in ("source", "optics", "motion", "processing", "output", "camera", "daq"):
        out.append(f"[{name}]")
        table = getattr(cfg, name)
        groups = group_of(type(table))
        shown = None if len(set(groups.values())) > 1 else next(iter(groups.values()), None)
        for key, value in table.model_dump().items():
            if groups.get(key, shown) != shown:  # a comment where the group changes
                shown = groups[key]
                out.append(f"# -- {GROUP_TITLES[shown].lower()} --")
            if value is None:  # TOML has no null: an absent key takes the default (None)
                out.append(f"# {key} = (not set)")
            elif isinstance(value, bool):
                out.append(f"{key} = {'true' if value else 'false'}")
            elif isinstance(value, str):
                out.append(f"{key} = {json.dumps(value)}")  # JSON escapes are TOML's
            else:
                out.append(f"{key} = {value!r}")
        out.append("")
    return "\n".join(out)
