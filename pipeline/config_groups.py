"""The groups of settings a scan configuration is made of: what is measured, how it runs,
and the simulated scanner's own parameters.

Each class here is one part of a table of the TOML file and names its group
(:attr:`ConfigModel.group`); :mod:`sffscan.pipeline.config` composes the parts into the
tables (``[optics]`` = :class:`Optics` + :class:`SimLens`, ...), and the configuration
reference lists every table's fields by group.

* **What is measured** (:class:`SourceKind`, :class:`Optics`, :class:`Motion`,
  :class:`Method`): these decide a mosaic's values; a resume refuses a mosaic made with
  others. The names of the focus operators and depth methods come from their registries
  (:data:`sffscan.stages.operators.FOCUS_OPERATORS`,
  :data:`sffscan.stages.depth.DEPTH_METHODS`).
* **How it runs** (:class:`Transport`, :class:`Execution`, :class:`Output`): how frames
  arrive, where and how the stages compute, where the mosaic is written. A resume may
  differ in the transport, the placement of the stages and the queue sizes
  (``sffscan.pipeline.run.RUN_ONLY``) and in the output table; it compares the rest.
* **The simulator's own parameters** (:class:`SimWorld`, :class:`SimLens`,
  :class:`SimMotion`), for ``source.kind = "sim"``: the world it renders, the lens's blur,
  noise, breathing, field curvature and vignetting, the stage's wobble. A real instrument
  has none of these (a calibration measures its lens: ``processing.calibration``). In the
  file they stay in the tables of the quantities they disturb (``[source]``, ``[optics]``,
  ``[motion]``), where every configuration of format version 1 has them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from sffscan.stages.depth import DEPTH_METHODS
from sffscan.stages.operators import FOCUS_OPERATORS, operator_reach

Group = Literal["measurement", "execution", "simulator"]

GROUP_TITLES: dict[str, str] = {
    "measurement": "What is measured",
    "execution": "How it runs",
    "simulator": "The simulator's own parameters",
}
"""Heading of each group of settings in the configuration reference."""


class ConfigModel(BaseModel):
    """Base of every configuration model: unknown keys, NaN and infinity are refused, and
    an assignment is validated as a loaded value is."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    group: ClassVar[Group | None] = None
    """The group of settings a part holds; ``None`` for a table composed of parts."""


def parts_of(table: type[BaseModel]) -> list[type[ConfigModel]]:
    """The parts a table's model is composed of (the classes that name their group), in
    the order of the table's fields; empty for a table not made of parts."""
    return [cls for cls in reversed(table.__mro__)
            if issubclass(cls, ConfigModel) and cls.__dict__.get("group") is not None]


def group_of(table: type[BaseModel]) -> dict[str, Group]:
    """The group of each field of a table made of parts, in the table's order."""
    return {name: part.group for part in parts_of(table) if part.group is not None
            for name in part.model_fields}


# --- what is measured ---------------------------------------------------------------------


if TYPE_CHECKING:  # a Literal made from a registry at run time is not a static type
    OperatorName = str
    DepthMethodName = str
else:
    OperatorName = Literal[tuple(FOCUS_OPERATORS)]
    DepthMethodName = Literal[tuple(DEPTH_METHODS)]


class SourceKind(ConfigModel):
    """Which scanner the frames come from."""

    group: ClassVar[Group | None] = "measurement"

    kind: Literal["sim", "camera", "tcp"] = Field(
        "sim", description="Frame source: 'sim' = simulated scanner, 'camera' = GenICam camera "
        "([camera] table), 'tcp' = frames sent by 'sffscan grab' to source.address")


class Optics(ConfigModel):
    """The camera's frames and the lens staircase: size, scale, focus levels, rate."""

    group: ClassVar[Group | None] = "measurement"

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

    @property
    def dtype(self) -> str:
        return "uint8" if self.bit_depth == 8 else "uint16"

    @property
    def max_value(self) -> float:
        return 255.0 if self.bit_depth == 8 else 1023.0

    def focus_heights_um(self) -> list[float]:
        return [self.z_min_um + k * self.z_step_um for k in range(self.n_levels)]


class Motion(ConfigModel):
    """The stage's travel: speed, the strip to cover, the passes."""

    group: ClassVar[Group | None] = "measurement"

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


class Method(ConfigModel):
    """How frames become heights: focus operator, depth method, registration, calibration."""

    group: ClassVar[Group | None] = "measurement"

    focus_operator: OperatorName = Field(
        "glvm", description="Focus measure operator: an acronym of Pertuz's toolbox "
        "(focusmeasure.m), any case")
    window: int = Field(9, ge=3, le=255, description="Focus measure window k (odd), px")
    depth_method: DepthMethodName = Field(
        "shape_select", description="Focus curve -> depth method (adaptive: about the "
        "median-filtered peak, the curve's maximum (3-point Gaussian) where the filtered "
        "peaks span <= 2 levels over the focus window, else the centroid of 11 levels; "
        "adaptive_centroid: the same with the centroid of 5 levels instead "
        "of the 3-point Gaussian where a block's curves do not pull a centroid from their "
        "maxima; shape_select (the default): spc or adaptive_centroid for each block of "
        "columns, spc where its focus curves are even and clean, except at the pixels "
        "within 1.5 curve widths of an end of the range; docs/depth-method.md, "
        "docs/depth-study.md)"
    )
    median_size: int = Field(11, ge=3, le=255, description="SPC median filter size (odd), px")
    registration: bool = Field(True, description="Refine speed offsets by phase correlation")
    registration_scale: int = Field(
        4, ge=1, le=16, description="Image reduction for registration (4 = quarter resolution)")
    calibration: str | None = Field(
        None, description="Calibration file (JSON, 'sffscan calibrate'): its z response maps "
        "focus levels to µm in place of optics.z_min_um + k * optics.z_step_um; its "
        "vignetting and magnification per level are corrected in the frames, its field "
        "curvature in the heights")

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


# --- how it runs --------------------------------------------------------------------------


class Transport(ConfigModel):
    """Frames received over the network (``source.kind = "tcp"``)."""

    group: ClassVar[Group | None] = "execution"

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


class Execution(ConfigModel):
    """Where and how the stages compute: backend, device, queues, blocks, processes."""

    group: ClassVar[Group | None] = "execution"

    backend: Literal["opencv", "torch"] = Field("opencv", description="Focus measure backend")
    device: str = Field("cpu", description="Torch device for backend 'torch' (cpu, cuda, ...)")
    queue_capacity: int = Field(8, ge=1, le=4096, description="Capacity of every inter-stage queue")
    block_columns: int = Field(128, ge=1, le=65536, description="Columns reduced to depth at once")
    execution: Literal["auto", "threads", "processes"] = Field(
        "auto", description="How the stages run: 'processes' = groups of stages in worker "
        "processes with frames in shared memory (uses several cores), 'threads' = one "
        "process (debugging, tiny scans), 'auto' = processes for scans of at least 2e8 "
        "pixels on a machine with 2 or more cores")
    workers: Annotated[int, Field(ge=1, le=64)] | Literal["auto"] = Field(
        1, description="Band workers of the focus measure and of the depth stage: each "
        "frame's rows split among that many workers (see bands), each measuring the focus "
        "of the rows it accumulates (OpenCV backend; with torch the depth stage's rows "
        "only), results bit-identical for any number; the registration measures a frame's "
        "pairs (one a lag) in as many threads, at most one a pair; 'auto' = the cores "
        "available less 2 (the registration and the main process), at least 1, at most 8. "
        "1 by default: on 2 cores N = 2 costs 1.09-1.27x the CPU of these stages in threads "
        "(bench/results/band_task_threads.md), which the other stages need; with bands = "
        "'processes' on a 16-core Xeon, 4 ran 152-161 "
        "frames/s on 8 cores against 99-101 with 1, and 'auto' (8) 179-184 on 16 cores "
        "(bench/results/parallel_async_h200.md)")

    bands: Literal["threads", "processes"] = Field(
        "threads", description="Where the band workers (workers > 1) run: 'threads' of the "
        "depth stage's process, or 'processes' (OpenCV backend; no GIL shared, for "
        "machines with a core per band), both running the same tasks on the depth stage's "
        "state, each band measuring the focus of the rows it accumulates (on 2 cores N = 2 "
        "took 1.23x the CPU of one band in processes, 1.27x in threads, "
        "bench/results/band_task_threads.md); the live view then measures the focus of the "
        "frames it shows itself")

    def bands_measure(self) -> bool:
        """Whether the depth stage's band workers measure the focus of the rows they
        accumulate (more than one band worker with the OpenCV backend: band processes, or
        band threads running the same tasks): the focus measure stage then passes the
        frames on unmeasured (:class:`~sffscan.stages.messages.RawColumns`)."""
        return self.backend == "opencv" and self.band_workers() > 1

    def band_workers(self) -> int:
        """The number of band workers: :attr:`workers`, 'auto' resolved on this machine."""
        if isinstance(self.workers, int):
            return self.workers
        from sffscan.pipeline.cores import auto_band_workers, cores_available

        return auto_band_workers(cores_available())


class Output(ConfigModel):
    """The Zarr store the height mosaic is written to."""

    group: ClassVar[Group | None] = "execution"

    path: str = Field("sffscan-mosaic.zarr", description="Zarr v3 group of the height mosaic")
    chunk_px: int = Field(256, ge=16, le=16384, description="Chunk edge of the mosaic arrays, px")
    overwrite: bool = Field(False, description="Replace an existing mosaic at path")


# --- the simulator's own parameters -------------------------------------------------------


class SimWorld(ConfigModel):
    """The simulated world and the seed of its texture and noise."""

    group: ClassVar[Group | None] = "simulator"

    seed: int = Field(0, ge=0, le=2**32 - 1,
                      description="Seed of the simulated world texture and sensor noise")
    world: Literal["plate", "sinusoid"] = Field(
        "plate", description="Simulated world: characterisation plate or sinusoidal surface"
    )
    plate_length_mm: float = Field(60.0, gt=0, le=2000,
                                   description="Length of the simulated plate, mm")
    plate_width_mm: float = Field(9.0, gt=0, le=2000,
                                  description="Width of the simulated plate, mm")


class SimLens(ConfigModel):
    """The simulated lens and sensor: blur, noise, breathing, field curvature, vignetting."""

    group: ClassVar[Group | None] = "simulator"

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
    blur_model: Literal["gather", "scatter"] = Field(
        "gather", description="Sim: a blur that varies over the frame, each pixel taking its "
        "own height's (gather) or each world point spreading its light by its own (scatter: "
        "the optics of a surface without occlusion; slower; not with field curvature)")

    @model_validator(mode="after")
    def _scatter_without_field_curvature(self) -> SimLens:
        if self.blur_model == "scatter" and self.field_curvature_um != 0:
            raise ValueError(f"blur_model 'scatter' is not built with field_curvature_um "
                             f"(got {self.field_curvature_um})")
        return self


class SimMotion(ConfigModel):
    """The simulated stage's wobble about its nominal travel."""

    group: ClassVar[Group | None] = "simulator"

    wobble_along_px: float = Field(0.0, ge=0, le=1000, description="Sim: wobble along, ±px")
    wobble_across_px: float = Field(0.0, ge=0, le=1000, description="Sim: wobble across, ±px")
    wobble_period_mm: float = Field(2.0, gt=0, le=1e5,
                                    description="Sim: wobble period, mm of travel")
