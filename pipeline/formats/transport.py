"""Frame transport over zmq: ``sffscan grab`` (sender) to ``sffscan scan --source`` (receiver).

Messages (``schemas/transport_message.v1.json``): a frame is three parts, a small JSON
header validated against :class:`TransportMessage` (the
:class:`~sffscan.stages.messages.FrameHeader`, dtype, shape and the CRC-32 of the pixels,
always present and always verified), an authentication tag, and the raw pixel bytes, C
order. The end of the stream is a message of its own (``kind = "end"``, with the number of
frames sent): header and tag. Never pickle.

Authentication: only the paired sender can deliver frames or end a scan.

- Loopback (``tcp://127.0.0.1``, ``localhost``, ``::1``, ``ipc://``): a per-scan secret. The
  receiver draws 32 random bytes when it starts and writes them to a pairing file only its
  user can read (:func:`pairing_path`: ``$XDG_RUNTIME_DIR`` or the temporary folder,
  ``sffscan-UID/``, mode 0600); it removes the file when it stops. The sender reads the file
  each time it (re)connects. The tag is the keyed BLAKE2b-256 of the header bytes; the
  header holds the frame's CRC-32, so the tag covers the pixels too. A third process that
  cannot read the file cannot forge a frame or an end message.
- Beyond loopback: CURVE (what libzmq ships: Curve25519 keys, encryption and a ZAP
  authenticator). ``sffscan keys`` makes the receiver's and the sender's key pairs in
  ``source.keys_dir``; the receiver accepts only the public keys in its ``authorized/``
  folder. Copy ``sender.key_secret`` and ``receiver.key`` to the sending machine's keys
  folder. The tag part is empty there (the connection is authenticated).

Robustness (the receiver, :mod:`sffscan.pipeline.formats.transport_receiver`): it refuses
messages larger than the configured frame (:func:`max_message_bytes`, zmq's ``MAXMSGSIZE``:
an oversized message drops its connection before it is buffered); an unauthenticated
message is dropped, counted and logged, never fatal (any local process can send one); a
malformed or out-of-order message of the paired sender is refused, logged and counted, and
the scan fails only once more than ``source.max_bad_messages`` of those were refused.
Frames past the receiver's plan are not processed and the scan is ``incomplete``. A sender
silent for ``source.idle_timeout_s`` after its first frame ends the stream without a count:
the scan ends ``incomplete``.

- Sockets: the receiver binds a PULL socket (it is the long-running scan), the sender
  connects a PUSH socket and reconnects by itself if the receiver restarts.
- The high-water marks (``hwm`` messages at each end) are the bounded queue: when the
  receiver falls behind, ``send`` blocks (with a stop check every 0.25 s), exactly like a
  ``block`` queue of the pipeline. ``CONFLATE`` is never set (it breaks multipart
  messages).
- Zero copy: the sender hands the image's buffer to zmq, which may read it after ``send``
  returns, so :meth:`FrameSender.send` takes the array over and marks it read-only; a
  source must give every frame a fresh array. The receiver's images are read-only views of
  the received message.
- Addresses: ``tcp://HOST:PORT`` or ``ipc://PATH``; the default is loopback
  (``tcp://127.0.0.1:5555``). Binding to another interface happens only when the address
  names it.
"""

from __future__ import annotations

import hmac
import logging
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field, RootModel, ValidationError
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.pipeline.formats.transport_auth import (
    auth_tag,
    check_pairing_dir,
    keys_dir_of,
    load_pair,
    load_public,
    read_pairing,
)
from sffscan.stages.messages import Frame, FrameHeader

logger = logging.getLogger(__name__)

DEFAULT_ADDRESS = "tcp://127.0.0.1:5555"
_WAIT_MS = 250  # longest single wait before the stop flag / timeout is checked again
#: largest header part accepted, bytes
MAX_HEADER_BYTES = 64 * 1024


class TransportError(RuntimeError):
    """A message that cannot be used, or a peer that went silent; names the frame."""


class Unauthenticated(TransportError):
    """A message that is not the paired sender's (dropped and counted, never fatal)."""


class FrameMessage(BaseModel):
    """Header part of a frame message; the third part holds the raw pixels."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["frame"] = "frame"
    header: FrameHeader
    dtype: Literal["uint8", "uint16"] = Field(description="Pixel type of the raw bytes")
    shape: tuple[int, int] = Field(description="Image (height, width), px")
    crc32: int = Field(ge=0, lt=2**32, description="zlib CRC-32 of the raw bytes")


class EndMessage(BaseModel):
    """End of the stream; header and tag only."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["end"] = "end"
    frames_sent: int = Field(ge=0, le=2**53, description="Frames sent before the end")
    last_frame_id: int | None = Field(
        None, ge=0, le=2**63 - 1,
        description="frame_id of the last frame sent (absent: none sent, or an older sender)")
    reason: str = Field("complete", max_length=4096,
                        description="'complete', or why the sender stopped")


class TransportMessage(RootModel[Annotated[FrameMessage | EndMessage,
                                           Field(discriminator="kind")]]):
    """First part of every message on the wire."""


# --- addresses ---------------------------------------------------------------------------


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


def max_message_bytes(cfg: ScanConfig) -> int:
    """Largest message part the receiver accepts: one configured frame (or a header)."""
    o = cfg.optics
    return max(o.height_px * o.width_px * np.dtype(o.dtype).itemsize, MAX_HEADER_BYTES)


# --- messages -----------------------------------------------------------------------------


def encode_frame(frame: Frame) -> tuple[bytes, np.ndarray]:
    """The header JSON and the C-contiguous image of a frame message."""
    img = np.ascontiguousarray(frame.image)
    if img.ndim != 2 or img.dtype.name not in ("uint8", "uint16"):
        raise TransportError(f"frame_id {frame.header.frame_id}: cannot send a "
                             f"{img.dtype} image of shape {img.shape}")
    msg = FrameMessage(header=frame.header, dtype=img.dtype.name,  # type: ignore[arg-type]
                       shape=(img.shape[0], img.shape[1]), crc32=zlib.crc32(img.data))
    return msg.model_dump_json().encode(), img


def _buffer(part: Any) -> memoryview:
    return part.buffer if hasattr(part, "buffer") else memoryview(part)


def decode_message(parts: list[Any], *, secret: bytes | None = None) -> Frame | EndMessage:
    """A received message (``zmq.Frame``s or bytes) as a :class:`Frame` or the end.

    With ``secret`` the second part must be the header's tag (:func:`auth_tag`), and a
    message that is not authenticated raises :class:`Unauthenticated` (whatever else is
    wrong with it); without it (CURVE: the connection is authenticated) the second part is
    ignored. Raises :class:`TransportError` naming the frame for anything else."""
    auth = Unauthenticated if secret is not None else TransportError
    if len(parts) not in (2, 3):
        raise auth(f"{len(parts)} message parts, expected 2 (end) or 3 (frame)")
    head = _buffer(parts[0])
    if head.nbytes > MAX_HEADER_BYTES:
        raise auth(f"header of {head.nbytes} bytes, more than {MAX_HEADER_BYTES}")
    head_bytes = bytes(head)
    if secret is not None and not hmac.compare_digest(bytes(_buffer(parts[1])),
                                                      auth_tag(secret, head_bytes)):
        raise Unauthenticated("message not authenticated: its tag does not match this "
                              "scan's secret (not the paired sender)")
    try:
        msg = TransportMessage.model_validate_json(head_bytes).root
    except ValidationError as err:
        raise TransportError(f"message header does not match the transport schema: "
                             f"{err.errors()[0]['msg']} at "
                             f"{'.'.join(str(p) for p in err.errors()[0]['loc'])}") from None
    if isinstance(msg, EndMessage):
        if len(parts) != 2:
            raise TransportError(f"end message of {len(parts)} parts, expected 2")
        return msg
    fid = msg.header.frame_id
    if len(parts) != 3:
        raise TransportError(f"frame_id {fid}: {len(parts)} message parts, expected 3")
    buf = _buffer(parts[2])
    if min(msg.shape) < 1:
        raise TransportError(f"frame_id {fid}: shape {msg.shape} is not an image shape")
    dtype = np.dtype(msg.dtype)
    expected = msg.shape[0] * msg.shape[1] * dtype.itemsize
    if buf.nbytes != expected:
        raise TransportError(f"frame_id {fid}: {buf.nbytes} bytes of pixels, expected "
                             f"{expected} for {msg.shape} {msg.dtype}")
    if zlib.crc32(buf) != msg.crc32:
        raise TransportError(f"frame_id {fid}: pixel checksum mismatch (corrupted in transit)")
    image = np.frombuffer(buf, dtype=dtype).reshape(msg.shape)
    return Frame(msg.header, image)


# --- sender -------------------------------------------------------------------------------


class FrameSender:
    """PUSH end: connects to ``address`` (or binds, ``bind=True``) and sends frames.

    Parameters
    ----------
    address : str
        zmq address of the receiver.
    hwm : int
        Send high-water mark, messages: how many frames may wait before ``send`` blocks.
    stop : threading.Event, optional
        Set it to abandon a blocked ``send`` (raises :class:`TransportError`).
    secret : bytes, optional
        Loopback: the receiver's per-scan secret; default: read from its pairing file
        (:func:`pairing_path`) at every (re)connection.
    keys_dir : str or Path, optional
        Beyond loopback: the folder with ``sender.key_secret`` and ``receiver.key``.
    curve : bool, optional
        Use CURVE (default: beyond loopback only).
    """

    def __init__(self, address: str = DEFAULT_ADDRESS, *, hwm: int = 8, bind: bool = False,
                 stop: threading.Event | None = None, secret: bytes | None = None,
                 keys_dir: str | Path | None = None, curve: bool | None = None) -> None:
        self.address = check_address(address)
        self.stop = stop if stop is not None else threading.Event()
        self.sent = 0
        self.last_frame_id: int | None = None  # of the last frame sent, for the end message
        self.bytes = 0
        self.blocked_s = 0.0
        self.loopback = not curve if curve is not None else is_loopback(address)
        self._fixed = secret is not None
        self.secret = secret
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.PUSH)
        self._sock.setsockopt(zmq.SNDHWM, hwm)
        self._sock.setsockopt(zmq.SNDTIMEO, _WAIT_MS)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._monitor: zmq.Socket | None = None
        try:
            if not self.loopback:
                folder = keys_dir_of(None, keys_dir)
                public, secret_key = load_pair(folder, "sender")
                self._sock.curve_secretkey = secret_key
                self._sock.curve_publickey = public
                self._sock.curve_serverkey = load_public(folder, "receiver")
            elif not self._fixed:
                check_pairing_dir(address)  # a folder others can write: refused now
                self._monitor = self._sock.get_monitor_socket(
                    zmq.EVENT_CONNECTED | zmq.EVENT_ACCEPTED)
            (self._sock.bind if bind else self._sock.connect)(address)
        except zmq.ZMQError as err:
            self.close(linger_s=0)
            raise ConfigError(f"{address}: {err}") from None
        except ConfigError:
            self.close(linger_s=0)
            raise

    def _refresh_secret(self, wait_ms: int = 0) -> None:
        """Read the receiver's pairing file after each (re)connection."""
        mon = self._monitor
        if mon is None:
            return
        if not mon.poll(wait_ms):
            return
        while mon.poll(0):
            mon.recv_multipart()
        secret = read_pairing(self.address)
        if secret is not None:
            if self.secret is not None and secret != self.secret:
                logger.info("transport: the receiver at %s restarted: new pairing secret",
                            self.address)
            self.secret = secret

    def _tag(self, header: bytes) -> bytes:
        return auth_tag(self.secret, header) if self.loopback and self.secret else b""

    def _send(self, head: bytes, rest: list[Any], *, timeout_s: float | None = None) -> None:
        t0 = time.perf_counter()
        while True:
            self._refresh_secret()
            if self.loopback and self.secret is None:  # no receiver yet: wait for one
                self._refresh_secret(_WAIT_MS)
                if self.secret is None:
                    self._check_wait(t0, timeout_s)
                    continue
            try:
                self._sock.send_multipart([head, self._tag(head), *rest], copy=False)
                break
            except zmq.Again:
                self._check_wait(t0, timeout_s)
        self.blocked_s += time.perf_counter() - t0

    def _check_wait(self, t0: float, timeout_s: float | None) -> None:
        if self.stop.is_set():
            raise TransportError(f"stopped while waiting for the receiver at {self.address}")
        if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
            raise TransportError(f"the receiver at {self.address} took no message for "
                                 f"{timeout_s:g} s")

    def send(self, frame: Frame) -> None:
        """Send one frame; the image array now belongs to zmq (it is made read-only)."""
        head, img = encode_frame(frame)
        if img is frame.image:
            img.flags.writeable = False  # zmq may still read it after send returns
        self._send(head, [img])
        self.sent += 1
        self.last_frame_id = frame.header.frame_id
        self.bytes += img.nbytes

    def end(self, reason: str = "complete", *, timeout_s: float | None = 10.0) -> None:
        """Send the end-of-stream message (waiting at most ``timeout_s`` for room)."""
        head = EndMessage(frames_sent=self.sent, last_frame_id=self.last_frame_id,
                          reason=reason[:4096]).model_dump_json().encode()
        self._send(head, [], timeout_s=timeout_s)

    def close(self, *, linger_s: float = 10.0) -> None:
        """Close, waiting up to ``linger_s`` for queued messages to leave."""
        if self._monitor is not None:
            self._sock.disable_monitor()
            self._monitor.close(linger=0)
            self._monitor = None
        if not self._sock.closed:
            self._sock.close(linger=int(linger_s * 1000))
        self._ctx.term()

    def __enter__(self) -> FrameSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(linger_s=0 if exc[0] is not None else 10.0)


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
                logger.info("grab: %d frames sent, %.1f frames/s, %.1f MB/s", sender.sent,
                            rate, sender.bytes / (now - t0) / 1e6)
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
