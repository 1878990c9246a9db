"""GenICam camera source (harvesters): frames with frame_id, time stamp and focus level.

:func:`camera_frames` is the frame feed of ``source.kind = "camera"``. It opens a GenTL
producer (``camera.cti``, else ``$SFFSCAN_CTI``, else the first entry of
``$GENICAM_GENTL64_PATH``), selects ``camera.device_index``, sets the region (the
configured frame size at ``camera.offset_*``), pixel format, exposure and the hardware
trigger (FrameStart on ``camera.trigger_line``, falling edge) where the device has those
nodes, and says which nodes are missing. It arms the camera, then starts the DAQ
(:mod:`pipeline.hardware.daq`; a simulated one by default), and copies every image out inside
harvesters' ``with fetch(timeout=...)`` block, so the producer's buffer goes back at once.

Synchronisation rule: the camera is armed before the DAQ's first trigger, and the first
falling edge is at the centre of staircase step 0. So the frame with (0-based, gap-aware)
frame_id k was exposed at focus level ``(k + camera.focus_phase) mod N``.

- frame_id: the device's frame counter (GenTL ``BUFFER_INFO_FRAMEID``) relative to the
  first frame, unwrapped modulo ``camera.frame_id_modulus`` (16-bit GigE Vision block ids
  wrap); a gap means lost frames, which the source stage counts and the focus volume turns
  into invalid columns. A device without a counter falls back to counting fetched frames,
  and lost frames can then not be detected (said in the notes).
- timestamp_ns: the device's time stamp relative to the first frame, or, where the device
  has none, the host's monotonic clock at fetch (marked in :class:`CameraStats`).
- Buffer underruns (GenTL ``STREAM_INFO_NUM_UNDERRUN``) are read at the end and reported.
- Passes: frames are assigned to passes by the scan plan's frame counts. The scan ends at
  the first frame_id past the plan's count; planned frames lost just before it are lost too.
- Refused before anything starts: an exposure past the trigger-to-next-step window
  (:func:`check_exposure`), and an untriggered camera with a real DAQ (unsynchronised).

The harvesters-specific code lives in :class:`HarvestersCamera` behind the small
:class:`Camera` protocol, so tests inject a fake one.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.pipeline.hardware.daq import Daq, open_daq, waveform_for
from sffscan.pipeline.hardware.lens_waveform import exposure_window_us, max_exposure_us
from sffscan.pipeline.plan import frame_count, pass_bounds_px
from sffscan.stages.frame_source import FrameBuffers, SourceFrames
from sffscan.stages.messages import Frame, FrameHeader

log = logging.getLogger(__name__)

#: pixel formats the pipeline takes, and the numpy dtype of their unpacked pixels
PIXEL_DTYPES = {"Mono8": "uint8", "Mono10": "uint16", "Mono12": "uint16", "Mono16": "uint16"}
#: largest bit depth each format can carry; frames must not exceed optics.bit_depth
PIXEL_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}


class CameraError(RuntimeError):
    """The camera cannot be opened, configured or read; the message says why."""


@dataclass(slots=True)
class RawImage:
    """One fetched image (a copy the producer no longer owns) and the device's counters."""

    image: np.ndarray
    frame_id: int | None
    timestamp_ns: int | None


class Camera(Protocol):
    """What the camera source needs from a camera."""

    def configure(self, cfg: ScanConfig) -> list[str]:
        """Apply region, pixel format, exposure, trigger; return notes (missing nodes)."""
        ...

    def start(self) -> None: ...

    def fetch(self, timeout_s: float, *, out: np.ndarray | None = None) -> RawImage:
        """The next image; raises :class:`CameraError` after ``timeout_s`` without one.

        ``out``: an array of the configured frame's shape and dtype (a slot of the process
        placement's frame ring) to copy the image into, returned as the image; an image of
        another shape or dtype comes as a new array instead (the source stage names it).
        """
        ...

    def underruns(self) -> int | None:
        """Buffer underruns counted by the producer, None where it does not count them."""
        ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


@dataclass
class CameraStats:
    """What the camera source saw; filled while it runs, printed when it ends."""

    frames: int = 0
    lost: int = 0
    gaps: int = 0
    lost_at_end: int = 0  # of ``lost``: planned frames after the last one delivered
    underruns: int | None = None
    timestamps: str = "device"  # or "host clock"
    frame_ids: str = "device"  # or "host count"
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        under = "not reported" if self.underruns is None else str(self.underruns)
        return (f"camera: {self.frames} frames, {self.lost} lost in {self.gaps} frame_id "
                f"gaps, buffer underruns {under}; frame_id from {self.frame_ids}, time "
                f"stamps from {self.timestamps}")


def find_cti(cfg: ScanConfig) -> Path:
    """The GenTL producer to load: camera.cti, $SFFSCAN_CTI, then $GENICAM_GENTL64_PATH."""
    cands: list[tuple[str, str]] = []
    if cfg.camera.cti:
        cands.append(("camera.cti", cfg.camera.cti))
    elif os.environ.get("SFFSCAN_CTI"):
        cands.append(("$SFFSCAN_CTI", os.environ["SFFSCAN_CTI"]))
    else:
        for entry in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
            if entry:
                p = Path(entry)
                ctis = sorted(p.glob("*.cti")) if p.is_dir() else [p]
                cands += [("$GENICAM_GENTL64_PATH", str(c)) for c in ctis]
    if not cands:
        raise ConfigError("camera.cti: no GenTL producer given (set camera.cti, $SFFSCAN_CTI "
                          "or $GENICAM_GENTL64_PATH)")
    origin, path = cands[0]
    if not Path(path).is_file():
        raise ConfigError(f"{origin}: GenTL producer {path} not found")
    return Path(path)


def check_exposure(cfg: ScanConfig, exposure_us: float, *, origin: str) -> list[str]:
    """Check an exposure against the staircase and the motion; notes for the user.

    With the hardware trigger the exposure starts at a step's centre and must end before
    the lens's next step (``1 / (2 fps)``, :func:`~.lens_waveform.exposure_window_us`):
    a longer one mixes two focus levels in one frame and raises :class:`CameraError`
    naming ``origin``. Longer than pixel scale / speed
    (:func:`pipeline.hardware.lens_waveform.max_exposure_us`) smears a point over more than one
    pixel: returned as a note, not refused.
    """
    o, m = cfg.optics, cfg.motion
    notes: list[str] = []
    window = exposure_window_us(o.fps)
    if cfg.camera.trigger and exposure_us > window:
        raise CameraError(f"{origin} = {exposure_us:g} µs: longer than the {window:.0f} µs "
                          f"from the trigger (step centre) to the lens's next step at "
                          f"{o.fps:g} fps; the frame would mix two focus levels")
    smear = max_exposure_us(o.pixel_um, m.speed_mm_s)
    if exposure_us > smear:
        notes.append(f"{origin} = {exposure_us:g} µs exceeds pixel scale / speed = "
                     f"{smear:.0f} µs: points smear over {exposure_us / smear:.1f} px")
    return notes


def _set(nm: Any, name: str, value: Any, missing: list[str]) -> bool:
    """Set node ``name`` if the device has it (and it is writable); note it otherwise."""
    if not nm.has_node(name):
        missing.append(name)
        return False
    node = getattr(nm, name)
    try:
        node.value = value
    except Exception as err:  # noqa: BLE001 - genicam raises many types; re-raised as ours
        raise CameraError(f"camera node {name} = {value!r} refused: {err}") from None
    return True


class HarvestersCamera:
    """A GenICam device through harvesters (opened here, released by :meth:`close`)."""

    def __init__(self, cti: Path, *, device_index: int = 0, num_buffers: int = 16) -> None:
        from harvesters.core import Harvester

        self._h = Harvester()
        self._ia: Any = None
        try:
            self._h.add_file(str(cti), check_existence=True)
            self._h.update()
            found = len(self._h.device_info_list)
            if device_index >= found:
                raise CameraError(f"camera.device_index = {device_index}, but {cti.name} "
                                  f"lists {found} device(s)")
            self._ia = self._h.create(device_index)
            self._ia.num_buffers = num_buffers
        except BaseException:
            self.close()
            raise

    def configure(self, cfg: ScanConfig) -> list[str]:
        nm = self._ia.remote_device.node_map
        c, o = cfg.camera, cfg.optics
        notes: list[str] = []
        missing: list[str] = []
        if c.pixel_format is not None:
            _set(nm, "PixelFormat", c.pixel_format, missing)
        fmt = str(nm.PixelFormat.value) if nm.has_node("PixelFormat") else "Mono8"
        if fmt not in PIXEL_DTYPES:
            raise CameraError(f"camera pixel format {fmt} is not supported; set "
                              f"camera.pixel_format to one of {', '.join(PIXEL_DTYPES)}")
        if PIXEL_DTYPES[fmt] != o.dtype or PIXEL_BITS[fmt] > max(o.bit_depth, 8):
            raise CameraError(f"camera pixel format {fmt} does not match optics.bit_depth = "
                              f"{o.bit_depth} (use Mono8 for 8, Mono10 for 10)")
        for name in ("OffsetX", "OffsetY"):  # an old offset may not leave room
            if nm.has_node(name):
                getattr(nm, name).value = 0
        for name, value in (("Width", o.width_px), ("Height", o.height_px)):
            node = getattr(nm, name)
            if not node.min <= value <= node.max:
                raise CameraError(f"optics.{name.lower()}_px = {value}: the camera's {name} "
                                  f"must lie in {node.min}..{node.max}")
            node.value = value
        if c.offset_x_px or nm.has_node("OffsetX"):
            _set(nm, "OffsetX", c.offset_x_px, missing)
        if c.offset_y_px or nm.has_node("OffsetY"):
            _set(nm, "OffsetY", c.offset_y_px, missing)
        exp_node = "ExposureTime" if nm.has_node("ExposureTime") else "ExposureTimeAbs"
        if c.exposure_us is not None:
            _set(nm, exp_node, c.exposure_us, missing)
        elif nm.has_node(exp_node):  # the device's own exposure must fit the step too
            notes += check_exposure(cfg, float(getattr(nm, exp_node).value),
                                    origin=f"the camera's {exp_node}")
        triggered = False
        if c.trigger:
            if all(nm.has_node(n) for n in ("TriggerMode", "TriggerSource",
                                            "TriggerActivation")):
                if nm.has_node("TriggerSelector"):
                    nm.TriggerSelector.value = "FrameStart"
                nm.TriggerMode.value = "On"
                nm.TriggerSource.value = c.trigger_line
                nm.TriggerActivation.value = "FallingEdge"
                triggered = True
            else:
                missing += [n for n in ("TriggerSelector", "TriggerMode", "TriggerSource",
                                        "TriggerActivation") if not nm.has_node(n)]
        if not triggered and cfg.daq.kind != "sim":
            why = ("camera.trigger = false" if not c.trigger else "the device lacks "
                   + ", ".join(dict.fromkeys(missing)))
            raise CameraError(f"the camera is not hardware-triggered ({why}), so its frames "
                              f"would not be synchronised with the lens staircase of daq.kind "
                              f"= '{cfg.daq.kind}'; set daq.kind = 'sim' to free-run")
        if not triggered:
            if nm.has_node("AcquisitionFrameRateEnable"):
                nm.AcquisitionFrameRateEnable.value = True
            if nm.has_node("AcquisitionFrameRate"):
                node = nm.AcquisitionFrameRate
                node.value = min(max(o.fps, node.min), node.max)
                if node.value != o.fps:
                    notes.append(f"free-run rate {node.value:g} fps differs from optics.fps = "
                                 f"{o.fps:g}")
            notes.append("free-run (no hardware trigger): focus levels follow the frame count "
                         "only")
        if missing:
            notes.insert(0, "device lacks nodes: " + ", ".join(dict.fromkeys(missing)))
        return notes

    def start(self) -> None:
        self._ia.start()

    def fetch(self, timeout_s: float, *, out: np.ndarray | None = None) -> RawImage:
        from genicam.gentl import TimeoutException

        try:
            with self._ia.fetch(timeout=timeout_s) as buf:
                comp = buf.payload.components[0]
                data = np.asarray(comp.data)
                if (out is not None and out.shape == (comp.height, comp.width)
                        and out.dtype == data.dtype):
                    # one copy, out of the producer's buffer into the caller's array
                    np.copyto(out, data.reshape(comp.height, comp.width))
                    image = out
                else:
                    image = np.array(data, copy=True).reshape(comp.height, comp.width)
                frame_id = _info(buf.module, "frame_id")
                ts = _info(buf, "timestamp_ns")
        except TimeoutException:
            raise CameraError(f"no frame within camera.fetch_timeout_s = {timeout_s:g} s (is "
                              "the trigger arriving?)") from None
        return RawImage(image, frame_id, ts)

    def underruns(self) -> int | None:
        try:
            return int(self._ia.data_streams[0].module.num_underrun)
        except Exception:  # noqa: BLE001 - a producer that does not count them
            return None

    def stop(self) -> None:
        if self._ia is not None and self._ia.is_acquiring():
            self._ia.stop()

    def close(self) -> None:
        ia, self._ia = self._ia, None
        if ia is not None:
            ia.destroy()
        self._h.reset()


def _info(obj: Any, name: str) -> int | None:
    """A GenTL buffer info, or None where the producer does not provide it."""
    try:
        return int(getattr(obj, name))
    except Exception:  # noqa: BLE001 - genicam NotAvailableException and friends
        return None


def open_camera(cfg: ScanConfig) -> HarvestersCamera:
    """The configured GenICam device."""
    return HarvestersCamera(find_cti(cfg), device_index=cfg.camera.device_index,
                            num_buffers=cfg.camera.num_buffers)


class FrameIdUnwrapper:
    """Device frame counter -> 0-based, wrap-free frame_id (gaps kept, lost frames counted).

    ``modulus`` is the counter's period (0: never wraps). A counter that stands still or
    goes back (without a wrap) raises :class:`CameraError`.
    """

    def __init__(self, modulus: int = 0) -> None:
        self.modulus = modulus
        self._last: int | None = None
        self.frame_id = -1
        self.lost = 0
        self.gaps = 0

    def __call__(self, raw: int) -> int:
        if self._last is None:
            self.frame_id = 0
        else:
            delta = raw - self._last
            if self.modulus:
                delta %= self.modulus
            if delta <= 0:
                raise CameraError(f"device frame counter went from {self._last} to {raw} "
                                  "(set camera.frame_id_modulus if it wraps)")
            if delta > 1:
                self.gaps += 1
                self.lost += delta - 1
            self.frame_id += delta
        self._last = raw
        return self.frame_id


def pass_of_frames(cfg: ScanConfig) -> list[int]:
    """First frame_id of each pass after the first, from the scan plan."""
    starts, total = [], 0
    for p in range(cfg.motion.passes):
        if p:
            starts.append(total)
        total += pass_bounds_px(cfg, p)[2]
    return starts


def camera_frames(cfg: ScanConfig, *, camera: Camera | None = None, daq: Daq | None = None,
                  stats: CameraStats | None = None) -> SourceFrames:
    """Frames from the configured camera until the scan plan's frame count (or
    ``camera.frames``) is reached; the device and the DAQ are released when the iterator
    ends or is closed.

    ``camera`` and ``daq`` replace the configured ones (tests); ``stats`` is filled as the
    frames go and its summary is logged (INFO) at the end. Each image is copied out of the
    producer's buffer into an array of the iterator's ``buffers``
    (:class:`~sffscan.stages.frame_source.FrameBuffers`: a new one, or a slot of the process
    placement's frame ring, which then takes no second copy).
    """
    buffers = FrameBuffers()
    st = stats if stats is not None else CameraStats()
    # the source stage counts the frame_id gaps it sees; those after the last frame, only
    # the camera knows
    return SourceFrames(_camera_frames(cfg, buffers, camera=camera, daq=daq, stats=st),
                        buffers, lost_at_end=lambda: st.lost_at_end)


def _camera_frames(cfg: ScanConfig, buffers: FrameBuffers, *, camera: Camera | None,
                   daq: Daq | None, stats: CameraStats | None) -> Iterator[Frame]:
    st = stats if stats is not None else CameraStats()
    o = cfg.optics
    shape, dtype = (o.height_px, o.width_px), np.dtype(o.dtype)
    n_total = cfg.camera.frames or frame_count(cfg)
    n_levels = cfg.optics.n_levels
    pass_starts = pass_of_frames(cfg)
    unwrap = FrameIdUnwrapper(cfg.camera.frame_id_modulus)
    cam = camera if camera is not None else open_camera(cfg)
    lens: Daq | None = None
    try:
        if cfg.camera.exposure_us is not None:
            st.notes += check_exposure(cfg, cfg.camera.exposure_us,
                                       origin="camera.exposure_us")
        st.notes += cam.configure(cfg)
        for note in st.notes:
            log.warning("camera: %s", note)
        waveform = waveform_for(cfg)
        cam.start()  # armed before the first trigger: the synchronisation rule
        lens = daq if daq is not None else open_daq(cfg)
        lens.start(waveform)
        t0_dev: int | None = None
        t0_host = 0
        fetched = 0
        last_fid = -1
        while True:
            # the array before the fetch: waiting for a ring slot never holds a camera buffer
            raw = cam.fetch(cfg.camera.fetch_timeout_s, out=buffers.empty(shape, dtype))
            host_ns = time.monotonic_ns()
            if raw.frame_id is None:
                st.frame_ids = "host count"
                fid = fetched
            else:
                fid = unwrap(raw.frame_id)
            fetched += 1
            if fid >= n_total:
                # planned frames between the last one yielded and the end were lost too
                missing = n_total - 1 - last_fid
                if missing > 0:
                    st.gaps, st.lost = st.gaps + 1, st.lost + missing
                    st.lost_at_end = missing
                break
            if fetched == 1:
                t0_dev, t0_host = raw.timestamp_ns, host_ns
            if raw.timestamp_ns is not None and t0_dev is not None:
                ts = raw.timestamp_ns - t0_dev
                if ts < 0:
                    raise CameraError(f"frame_id {fid}: device time stamp went back by "
                                      f"{-ts} ns")
            else:
                st.timestamps = "host clock"
                ts = host_ns - t0_host
            pass_index = sum(1 for s in pass_starts if fid >= s)
            st.frames += 1
            st.lost, st.gaps = unwrap.lost, unwrap.gaps
            last_fid = fid
            yield Frame(FrameHeader(frame_id=fid, timestamp_ns=ts,
                                    focus_index=(fid + cfg.camera.focus_phase) % n_levels,
                                    pass_index=pass_index), raw.image)
    finally:
        try:
            if lens is not None:
                try:
                    lens.stop()
                finally:
                    lens.close()
        finally:
            try:
                st.underruns = cam.underruns()
                cam.stop()
            finally:
                cam.close()
            log.info(st.summary())
