"""Scan configuration: typed models, TOML loading and feasibility checks.

A configuration has five tables: ``[source]``, ``[optics]``, ``[motion]``,
``[processing]`` and ``[output]`` (see README, "Configuration reference"). Every error
names the field, for example ``optics.pixel_um``.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from sffscan.pipeline.hardware.config import CameraConfig, DaqConfig


class ConfigError(ValueError):
    """An invalid or impossible configuration; the message names the field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class SourceConfig(_Model):
    kind: Literal["sim", "camera", "tcp"] = Field(
        "sim", description="Frame source: 'sim' = simulated scanner, 'camera' = GenICam camera "
        "([camera] table), 'tcp' = frames sent by 'sffscan grab' to source.address")
    address: str = Field("tcp://127.0.0.1:5555", description="zmq address of 'sffscan grab' "
                         "(tcp:// or ipc://), for kind 'tcp'")
    idle_timeout_s: float = Field(
        30.0, gt=0, le=86400, description="Transport: a sender silent this long after its first "
        "frame has stopped; the stream ends there and the scan is 'incomplete', s")
    max_bad_messages: int = Field(
        100, ge=0, le=10**6, description="Transport: malformed or unauthenticated messages "
        "refused (and counted) before the scan fails")
    keys_dir: str | None = Field(
        None, description="Transport beyond loopback: folder of the CURVE keys made by "
        "'sffscan keys' (default $XDG_CONFIG_HOME/sffscan/keys, else ~/.config/sffscan/keys)")
    seed: int = Field(0, ge=0, le=2**32 - 1,
                      description="Seed of the simulated world texture and sensor noise")
    world: Literal["plate", "sinusoid"] = Field(
        "plate", description="Simulated world: characterisation plate or sinusoidal surface"
    )
    plate_length_mm: float = Field(60.0, gt=0, le=2000,
                                   description="Length of the simulated plate, mm")
    plate_width_mm: float = Field(9.0, gt=0, le=2000,
                                  description="Width of the simulated plate, mm")


class OpticsConfig(_Model):
    width_px: int = Field(1280, ge=32, le=65536, description="Frame width (along the motion), px")
    height_px: int = Field(1024, ge=32, le=65536,
                           description="Frame height (across the motion), px")
    pixel_um: float = Field(8.5, gt=0, le=10000, description="Object-side pixel scale, µm/px")
    n_levels: int = Field(50, ge=3, le=255, description="Focus levels N of the lens staircase")
    z_min_um: float = Field(0.0, ge=-1e6, le=1e6, description="Height in focus at level 0, µm")
    z_step_um: float = Field(200.0, gt=0, le=1e5,
                             description="Height step between focus levels, µm")
    fps: float = Field(150.0, gt=0, le=1e6, description="Camera frame rate, frames/s")
    bit_depth: Literal[8, 10] = Field(10, description="8 -> uint8 frames, 10 -> 10-bit in uint16")
    psf_s0_px: float = Field(0.6, ge=0, le=100, description="Sim: PSF sigma in focus, px")
    psf_c_px_per_um: float = Field(0.004, gt=0, le=10,
                                   description="Sim: PSF sigma growth, px per µm")
    sigma_max_px: float = Field(16.0, gt=0, le=256,
                                description="Sim: largest PSF sigma rendered, px")
    noise_sigma: float = Field(0.005, ge=0, le=1, description="Sim: sensor noise std, full scale")
    magnification_per_mm: float = Field(
        0.0, gt=-0.1, lt=0.1, description="Sim: relative change of the magnification per mm of "
        "focus height, about the optical centre (focus breathing), 1/mm; 0 = telecentric")
    magnification_ref_um: float | None = Field(
        None, ge=-1e6, le=1e6, description="Sim: focus height where the magnification is 1, "
        "µm; default the middle of the focus range")
    field_curvature_um: float = Field(
        0.0, ge=-1e5, le=1e5, description="Sim: surface of best focus above the nominal focus "
        "at the frame corner (quadratic in the radius from the centre), µm; 0 = flat field")
    vignetting: float = Field(0.0, ge=0, lt=1, description="Sim: illumination lost at the "
                              "frame corner (quadratic in the radius), fraction")

    @property
    def dtype(self) -> str:
        return "uint8" if self.bit_depth == 8 else "uint16"

    @property
    def max_value(self) -> float:
        return 255.0 if self.bit_depth == 8 else 1023.0

    def focus_heights_um(self) -> list[float]:
        return [self.z_min_um + k * self.z_step_um for k in range(self.n_levels)]

    def magnification_reference_um(self) -> float:
        """Focus height where the simulated magnification is 1, µm."""
        if self.magnification_ref_um is not None:
            return self.magnification_ref_um
        return self.z_min_um + 0.5 * (self.n_levels - 1) * self.z_step_um


class MotionConfig(_Model):
    speed_mm_s: float = Field(15.0, gt=0, le=10000, description="Stage speed, mm/s")
    x_start_mm: float = Field(0.0, ge=-1e5, le=1e5,
                              description="Start of the strip to cover completely, mm")
    x_end_mm: float = Field(60.0, ge=-1e5, le=1e5,
                            description="End of the strip to cover completely, mm")
    y_start_mm: float = Field(0.0, ge=-1e5, le=1e5,
                              description="World y of the first pass's first row, mm")
    passes: int = Field(1, ge=1, le=10000, description="Parallel passes, stepped along y")
    pass_overlap: float = Field(0.15, ge=0, lt=1, description="Pass overlap, fraction")
    serpentine: bool = Field(True, description="Alternate the direction of successive passes")
    wobble_along_px: float = Field(0.0, ge=0, le=1000, description="Sim: wobble along, ±px")
    wobble_across_px: float = Field(0.0, ge=0, le=1000, description="Sim: wobble across, ±px")
    wobble_period_mm: float = Field(2.0, gt=0, le=1e5,
                                    description="Sim: wobble period, mm of travel")


class ProcessingConfig(_Model):
    focus_operator: Literal[
        "acmo", "bren", "cheb", "cont", "curv", "dcte", "dctm", "dctr", "eigv", "gder", "gllv",
        "glva", "glvm", "glvn", "grae", "gras", "grat", "helm", "hise", "hisr", "lapd", "lape",
        "lapm", "lapv", "sfil", "sfrq", "teng", "tenv", "tenv_std", "vola", "vols", "wavr",
        "wavs", "wavv",
    ] = Field("glvm", description="Focus measure operator: an acronym of Pertuz's toolbox "
              "(focusmeasure.m), any case")
    window: int = Field(9, ge=3, le=255, description="Focus measure window k (odd), px")
    depth_method: Literal["argmax", "gauss3", "quadratic3", "centroid", "pc", "spc",
                          "wcentroid", "adaptive"] = Field(
        "adaptive", description="Focus curve -> depth method (adaptive: about the "
        "median-filtered peak, the curve's maximum (3-point Gaussian) where the filtered "
        "peaks span <= 2 levels over the focus window, else the centroid of 11 levels)"
    )
    median_size: int = Field(11, ge=3, le=255, description="SPC median filter size (odd), px")
    registration: bool = Field(True, description="Refine speed offsets by phase correlation")
    registration_scale: int = Field(
        4, ge=1, le=16, description="Image reduction for registration (4 = quarter resolution)")
    backend: Literal["opencv", "torch"] = Field("opencv", description="Focus measure backend")
    device: str = Field("cpu", description="Torch device for backend 'torch' (cpu, cuda, ...)")
    calibration: str | None = Field(
        None, description="Calibration file (JSON, 'sffscan calibrate'): its z response maps "
        "focus levels to µm in place of optics.z_min_um + k * optics.z_step_um; its "
        "vignetting and magnification per level are corrected in the frames, its field "
        "curvature in the heights")
    queue_capacity: int = Field(8, ge=1, le=4096, description="Capacity of every inter-stage queue")
    block_columns: int = Field(128, ge=1, le=65536, description="Columns reduced to depth at once")
    execution: Literal["auto", "threads", "processes"] = Field(
        "auto", description="How the stages run: 'processes' = groups of stages in worker "
        "processes with frames in shared memory (uses several cores), 'threads' = one "
        "process (debugging, tiny scans), 'auto' = processes for scans of at least 2e8 "
        "pixels on a machine with 2 or more cores")

    @field_validator("focus_operator", mode="before")
    @classmethod
    def _lower(cls, v: object) -> object:
        return v.lower() if isinstance(v, str) else v

    @field_validator("window", "median_size")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"must be odd, got {v}")
        return v

    @property
    def focus_reach_px(self) -> int:
        """How far the frame border reaches into the focus measure, px.

        GLVM filters twice with the k x k box (reach 2 * (k // 2)); TENV is a 3 x 3 Sobel
        then the box (reach k // 2 + 1); every operator's reach is
        :func:`sffscan.stages.operators.operator_reach`. Columns and rows closer to the
        border than this see the padded border and are not used.
        """
        from sffscan.stages.operators import operator_reach  # torch-free

        return operator_reach(self.focus_operator, self.window)

    @property
    def edge_margin_px(self) -> int:
        """Frame border the scan plan leaves unused, px.

        The focus measure's reach + 1, plus 2 px when registration is on: the focus volume
        keeps every pixel beyond the reach, so a frame that registration places up to 3 px
        off (measured: at most 2 px without any wobble) still covers the planned strip at
        every focus level.
        """
        return self.focus_reach_px + 1 + (2 if self.registration else 0)


class OutputConfig(_Model):
    path: str = Field("sffscan-mosaic.zarr", description="Zarr v3 group of the height mosaic")
    chunk_px: int = Field(256, ge=16, le=16384, description="Chunk edge of the mosaic arrays, px")
    overwrite: bool = Field(False, description="Replace an existing mosaic at path")


class ScanConfig(_Model):
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
        for key, value in getattr(cfg, name).model_dump().items():
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
