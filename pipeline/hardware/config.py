"""Configuration tables of the real hardware: ``[camera]`` (GenICam via harvesters) and
``[daq]`` (the lens staircase and camera trigger via nidaqmx).

Both are part of :class:`sffscan.pipeline.config.ScanConfig`; with the defaults (``source.kind =
"sim"``, ``daq.kind = "sim"``) no hardware is touched. The camera's region is the
configured frame size (``optics.width_px`` x ``optics.height_px``); its free-run frame rate,
where the camera runs without a trigger, is ``optics.fps``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class CameraConfig(_Model):
    cti: str | None = Field(
        None, description="GenTL producer (.cti) path; default: $SFFSCAN_CTI, then the first "
        "entry of $GENICAM_GENTL64_PATH")
    device_index: int = Field(0, ge=0, le=1023, description="Index of the device among those found")
    pixel_format: str | None = Field(None, description="GenICam PixelFormat (Mono8, Mono10, ..."
                                     "); default: leave the device's")
    offset_x_px: int = Field(0, ge=0, le=65535, description="Region offset along x (OffsetX), px")
    offset_y_px: int = Field(0, ge=0, le=65535, description="Region offset along y (OffsetY), px")
    exposure_us: float | None = Field(None, gt=0, le=1e7, description="Exposure time, µs; default: "
                                      "leave the device's")
    trigger: bool = Field(True, description="Hardware trigger (falling edge) when the device "
                          "has the nodes")
    trigger_line: str = Field("Line0", description="TriggerSource line of the DAQ's square wave")
    fetch_timeout_s: float = Field(2.0, gt=0, le=3600, description="Longest wait for one frame, s")
    frames: int | None = Field(None, ge=1, le=10**9,
                               description="Frames to acquire; default: the scan "
                               "plan's frame count")
    frame_id_modulus: int = Field(
        0, ge=0, le=2**48, description="Wrap-around of the device's frame counter (65536 for "
        "a 16-bit GigE Vision block id); 0 = a 64-bit counter that never wraps")
    focus_phase: int = Field(0, ge=0, le=254,
                             description="Focus level of the first frame after the "
                             "DAQ starts (0 when the staircase starts at level 0)")
    num_buffers: int = Field(16, ge=1, le=1024, description="Acquisition buffers announced to the "
                             "GenTL producer")


class DaqConfig(_Model):
    kind: Literal["sim", "nidaqmx"] = Field("sim", description="'sim' = no DAQ; 'nidaqmx' = "
                                             "NI DAQ drives the lens and triggers the camera")
    device: str = Field("Dev1", description="NI-DAQmx device name")
    lens_channel: str = Field("ao0", description="Analogue output driving the lens")
    trigger_channel: str = Field("ao1", description="Output of the camera trigger square wave")
    lens_v_min: float = Field(0.0, ge=0, le=10,
                              description="Lens driver voltage at focus level 0, V")
    lens_v_max: float = Field(5.0, ge=0, le=10,
                              description="Lens driver voltage at focus level N-1, V")
    lens_dac_bits: int = Field(10, ge=1, le=16, description="Resolution of the lens driver's "
                               "analogue input, bits")
    lens_full_scale_v: float = Field(5.0, gt=0, le=10,
                                     description="Lens driver input range 0..full "
                                     "scale, V (the driver quantises it to lens_dac_bits)")
    trigger_v_high: float = Field(5.0, gt=0, le=10, description="High level of the trigger square "
                                  "wave, V (TTL)")
    samples_per_step: int = Field(20, ge=2, le=10000,
                                  description="Output samples per staircase step "
                                  "(even: the trigger's falling edge sits on the step's "
                                  "centre sample)")
    start_trigger: str | None = Field(None, description="Digital start trigger terminal "
                                      "(e.g. /Dev1/PFI0); default: start at once")
    clock_source: str | None = Field(None, description="Sample clock terminal; default: the "
                                     "device's onboard clock")

    @field_validator("samples_per_step")
    @classmethod
    def _even(cls, v: int) -> int:
        if v % 2:
            raise ValueError(f"must be even, got {v}")
        return v

    @model_validator(mode="after")
    def _check(self) -> DaqConfig:
        for name in ("lens_v_min", "lens_v_max"):
            v = getattr(self, name)
            if not 0.0 <= v <= self.lens_full_scale_v:
                raise ValueError(f"{name} = {v:g} V lies outside the driver's input range "
                                 f"0..{self.lens_full_scale_v:g} V")
        if self.lens_v_max <= self.lens_v_min:
            raise ValueError("lens_v_max must be greater than lens_v_min")
        return self
