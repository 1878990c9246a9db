"""Configuration tables of the real hardware: ``[camera]`` (GenICam via harvesters) and
``[daq]`` (the lens staircase and camera trigger via nidaqmx).

Both are part of :class:`pipeline.config.ScanConfig`; with the defaults (``source.kind =
"sim"``, ``daq.kind = "sim"``) no hardware is touched.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class CameraConfig(_Model):
    cti: str | None = Field(
        None, description="GenTL producer (.cti) path; default: $SFFSCAN_CTI, then the first "
        "entry of $GENICAM_GENTL64_PATH")
    device_index: int = Field(0, ge=0, description="Index of the device among those found")
    pixel_format: str | None = Field(None, description="GenICam PixelFormat (Mono8, Mono10, ..."
                                     "); default: leave the device's")
    exposure_us: float | None = Field(None, gt=0, description="Exposure time, µs; default: "
                                      "leave the device's")
    trigger: bool = Field(True, description="Hardware trigger (falling edge) when the device "
                          "has the nodes")
    trigger_line: str = Field("Line0", description="TriggerSource line of the DAQ's square wave")
    fetch_timeout_s: float = Field(2.0, gt=0, description="Longest wait for one frame, s")


class DaqConfig(_Model):
    kind: Literal["sim", "nidaqmx"] = Field("sim", description="'sim' = no DAQ; 'nidaqmx' = "
                                             "NI DAQ drives the lens and triggers the camera")
    device: str = Field("Dev1", description="NI-DAQmx device name")
    lens_channel: str = Field("ao0", description="Analogue output driving the lens")
    trigger_channel: str = Field("ao1", description="Output of the camera trigger square wave")
    lens_v_min: float = Field(0.0, description="Lens driver voltage at focus level 0, V")
    lens_v_max: float = Field(5.0, description="Lens driver voltage at focus level N-1, V")
    lens_dac_bits: int = Field(10, ge=1, le=16, description="Resolution of the lens driver's "
                               "analogue input, bits")
