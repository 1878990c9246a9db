"""Frame transport over zmq: ``sffscan grab`` (sender) to ``sffscan scan --source`` (receiver).

Every message has two parts: a small JSON header validated against
:class:`TransportMessage` (``schemas/transport_message.v1.json``: the
:class:`~sffscan.pipeline.messages.FrameHeader`, dtype, shape and a CRC-32 of the pixels) and the
raw pixel bytes, C order. Never pickle. The end of the stream is a message of its own
(``kind = "end"``, with the number of frames sent).

- Sockets: the receiver binds a PULL socket (it is the long-running scan), the sender
  connects a PUSH socket and reconnects by itself if the receiver restarts.
- The high-water marks (``hwm`` messages at each end) are the bounded queue: when the
  receiver falls behind, ``send`` blocks (with a stop check every 0.25 s), exactly like a
  ``block`` queue of the pipeline. ``CONFLATE`` is never set (it breaks multipart
  messages).
- Zero copy: the sender hands the image's buffer to zmq, which may read it after ``send``
  returns, so :meth:`FrameSender.send` takes the array over and marks it read-only; a
  source must give every frame a fresh array (the camera source copies each image out of
  the producer's buffer). The receiver's images are read-only views of the received
  message.
- Addresses: ``tcp://HOST:PORT`` or ``ipc://PATH``; the default is loopback
  (``tcp://127.0.0.1:5555``). Binding to another interface happens only when the address
  names it.
"""

from __future__ import annotations

import sys
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field, RootModel, ValidationError
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.pipeline.messages import Frame, FrameHeader

DEFAULT_ADDRESS = "tcp://127.0.0.1:5555"
_WAIT_MS = 250  # longest single wait before the stop flag / timeout is checked again


class TransportError(RuntimeError):
    """A message that cannot be used, or a peer that went silent; names the frame."""


class FrameMessage(BaseModel):
    """Header part of a frame message; the second part holds the raw pixels."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["frame"] = "frame"
    header: FrameHeader
    dtype: Literal["uint8", "uint16"] = Field(description="Pixel type of the raw bytes")
    shape: tuple[int, int] = Field(description="Image (height, width), px")
    crc32: int | None = Field(None, ge=0, description="zlib CRC-32 of the raw bytes, or null")


class EndMessage(BaseModel):
    """End of the stream; a single-part message."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["end"] = "end"
    frames_sent: int = Field(ge=0, description="Frames sent before the end")
    reason: str = Field("complete", description="'complete', or why the sender stopped")


class TransportMessage(RootModel[Annotated[FrameMessage | EndMessage,
                                           Field(discriminator="kind")]]):
    """First part of every message on the wire."""


def check_address(address: str) -> str:
    """``address`` if it is a zmq tcp:// or ipc:// address, else :class:`ConfigError`."""
    if not address.startswith(("tcp://", "ipc://")) or len(address) <= 6:
        raise ConfigError(f"{address!r}: expected a zmq address tcp://HOST:PORT or ipc://PATH")
    return address


def is_loopback(address: str) -> bool:
    if address.startswith("ipc://"):
        return True
    host = address[len("tcp://"):].rsplit(":", 1)[0]
    return host in ("127.0.0.1", "localhost", "::1", "[::1]")


def encode_frame(frame: Frame, *, checksum: bool = True) -> tuple[bytes, np.ndarray]:
    """The two parts of a frame message: header JSON and the C-contiguous image."""
    img = np.ascontiguousarray(frame.image)
    if img.ndim != 2 or img.dtype.name not in ("uint8", "uint16"):
        raise TransportError(f"frame_id {frame.header.frame_id}: cannot send a "
                             f"{img.dtype} image of shape {img.shape}")
    crc = zlib.crc32(img.data) if checksum else None
    msg = FrameMessage(header=frame.header, dtype=img.dtype.name,  # type: ignore[arg-type]
                       shape=(img.shape[0], img.shape[1]), crc32=crc)
    return msg.model_dump_json().encode(), img


def decode_message(parts: list[Any]) -> Frame | EndMessage:
    """A received message (``zmq.Frame``s or bytes) as a :class:`Frame` or the end."""
    try:
        msg = TransportMessage.model_validate_json(bytes(parts[0].buffer if hasattr(
            parts[0], "buffer") else parts[0])).root
    except ValidationError as err:
        raise TransportError(f"message header does not match the transport schema: "
                             f"{err.errors()[0]['msg']} at "
                             f"{'.'.join(str(p) for p in err.errors()[0]['loc'])}") from None
    if isinstance(msg, EndMessage):
        return msg
    fid = msg.header.frame_id
    if len(parts) != 2:
        raise TransportError(f"frame_id {fid}: {len(parts)} message parts, expected 2")
    buf = parts[1].buffer if hasattr(parts[1], "buffer") else memoryview(parts[1])
    if min(msg.shape) < 1:
        raise TransportError(f"frame_id {fid}: shape {msg.shape} is not an image shape")
    dtype = np.dtype(msg.dtype)
    expected = msg.shape[0] * msg.shape[1] * dtype.itemsize
    if buf.nbytes != expected:
        raise TransportError(f"frame_id {fid}: {buf.nbytes} bytes of pixels, expected "
                             f"{expected} for {msg.shape} {msg.dtype}")
    if msg.crc32 is not None and zlib.crc32(buf) != msg.crc32:
        raise TransportError(f"frame_id {fid}: pixel checksum mismatch (corrupted in transit)")
    image = np.frombuffer(buf, dtype=dtype).reshape(msg.shape)
    return Frame(msg.header, image)


class FrameSender:
    """PUSH end: connects to ``address`` (or binds, ``bind=True``) and sends frames.

    Parameters
    ----------
    address : str
        zmq address of the receiver.
    hwm : int
        Send high-water mark, messages: how many frames may wait before ``send`` blocks.
    checksum : bool
        Put a CRC-32 of the pixels in every header.
    stop : threading.Event, optional
        Set it to abandon a blocked ``send`` (raises :class:`TransportError`).
    """

    def __init__(self, address: str = DEFAULT_ADDRESS, *, hwm: int = 8, bind: bool = False,
                 checksum: bool = True, stop: threading.Event | None = None) -> None:
        self.address = check_address(address)
        self.checksum = checksum
        self.stop = stop if stop is not None else threading.Event()
        self.sent = 0
        self.bytes = 0
        self.blocked_s = 0.0
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.PUSH)
        self._sock.setsockopt(zmq.SNDHWM, hwm)
        self._sock.setsockopt(zmq.SNDTIMEO, _WAIT_MS)
        self._sock.setsockopt(zmq.LINGER, 0)
        try:
            (self._sock.bind if bind else self._sock.connect)(address)
        except zmq.ZMQError as err:
            self.close(linger_s=0)
            raise ConfigError(f"{address}: {err}") from None

    def _send(self, parts: list[Any], *, timeout_s: float | None = None) -> None:
        t0 = time.perf_counter()
        while True:
            try:
                self._sock.send_multipart(parts, copy=False)
                break
            except zmq.Again:
                if self.stop.is_set():
                    raise TransportError(f"stopped while waiting for the receiver at "
                                         f"{self.address}") from None
                if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
                    raise TransportError(f"the receiver at {self.address} took no message "
                                         f"for {timeout_s:g} s") from None
        self.blocked_s += time.perf_counter() - t0

    def send(self, frame: Frame) -> None:
        """Send one frame; the image array now belongs to zmq (it is made read-only)."""
        head, img = encode_frame(frame, checksum=self.checksum)
        if img is frame.image:
            img.flags.writeable = False  # zmq may still read it after send returns
        self._send([head, img])
        self.sent += 1
        self.bytes += img.nbytes

    def end(self, reason: str = "complete", *, timeout_s: float | None = 10.0) -> None:
        """Send the end-of-stream message (waiting at most ``timeout_s`` for room)."""
        self._send([EndMessage(frames_sent=self.sent, reason=reason).model_dump_json()
                    .encode()], timeout_s=timeout_s)

    def close(self, *, linger_s: float = 10.0) -> None:
        """Close, waiting up to ``linger_s`` for queued messages to leave."""
        if not self._sock.closed:
            self._sock.close(linger=int(linger_s * 1000))
        self._ctx.term()

    def __enter__(self) -> FrameSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(linger_s=0 if exc[0] is not None else 10.0)


@dataclass
class ReceiverStats:
    frames: int = 0
    bytes: int = 0
    ended: bool = False
    frames_sent: int | None = None
    lost: int = 0  # frames the end message says were sent that never arrived here


def receive_frames(address: str, cfg: ScanConfig, *, hwm: int | None = None,
                   idle_timeout_s: float = 30.0, first_timeout_s: float | None = None,
                   stats: ReceiverStats | None = None) -> Iterator[Frame]:
    """Frames sent by ``sffscan grab`` to ``address`` (bound here), until the end message
    (an end message saying the sender failed raises :class:`TransportError`).

    The receive high-water mark defaults to ``processing.queue_capacity``. Raises
    :class:`TransportError` when no message comes for ``idle_timeout_s`` after the first
    one (or ``first_timeout_s`` before it; None waits for the sender indefinitely), or
    for a message that fails its schema or checksum. The socket is closed when the
    generator is closed, so a new receiver may bind the address again.
    """
    check_address(address)
    st = stats if stats is not None else ReceiverStats()
    if not is_loopback(address):
        print(f"transport: listening on {address}, beyond this machine", file=sys.stderr)
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PULL)
    sock.setsockopt(zmq.RCVHWM, hwm if hwm is not None else cfg.processing.queue_capacity)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        try:
            sock.bind(address)
        except zmq.ZMQError as err:
            raise ConfigError(f"{address}: cannot listen: {err}") from None
        last = time.monotonic()
        while True:
            if not sock.poll(_WAIT_MS):
                limit = idle_timeout_s if st.frames else first_timeout_s
                if limit is not None and time.monotonic() - last > limit:
                    after = f"after {st.frames} frames" if st.frames else "at all"
                    raise TransportError(f"no message from the sender at {address} for "
                                         f"{limit:g} s ({after}); is 'sffscan grab' running?")
                continue
            parts = sock.recv_multipart(copy=False)
            last = time.monotonic()
            item = decode_message(parts)
            if isinstance(item, EndMessage):
                st.ended, st.frames_sent = True, item.frames_sent
                st.lost = max(item.frames_sent - st.frames, 0)
                if st.lost:  # at a receiver restart; also after the last frame_id seen
                    print(f"transport: received {st.frames} of the {item.frames_sent} frames "
                          f"sent: {st.lost} lost in transit", file=sys.stderr)
                if item.reason != "complete":  # the scan fails, keeping what it measured
                    raise TransportError(f"the sender stopped after {item.frames_sent} "
                                         f"frames: {item.reason}")
                return
            st.frames += 1
            st.bytes += item.image.nbytes
            yield item
    finally:
        sock.close(linger=0)
        ctx.term()


def stream_frames(frames: Iterator[Frame], sender: FrameSender, *,
                  progress_every_s: float = 5.0) -> int:
    """Send every frame of ``frames``, then the end message; returns frames sent."""
    t0 = last = time.perf_counter()
    reason = "complete"
    try:
        for frame in frames:
            sender.send(frame)
            now = time.perf_counter()
            if now - last >= progress_every_s:
                last = now
                rate = sender.sent / (now - t0)
                print(f"grab: {sender.sent} frames sent, {rate:.1f} frames/s, "
                      f"{sender.bytes / (now - t0) / 1e6:.1f} MB/s", file=sys.stderr)
    except BaseException as err:
        reason = f"{type(err).__name__}: {err}" if not isinstance(err, KeyboardInterrupt) \
            else "interrupted"
        raise
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()
        try:  # a failed stream's end is best effort: the receiver may be gone
            sender.end(reason, timeout_s=10.0 if reason == "complete" else 2.0)
        except TransportError:
            pass
    return sender.sent

