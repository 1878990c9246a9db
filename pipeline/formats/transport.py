"""Frame transport over zmq: ``sffscan grab`` (sender) to ``sffscan scan --source`` (receiver).

Messages (``schemas/transport_message.v1.json``): a frame is three parts, a small JSON
header validated against :class:`TransportMessage` (the
:class:`~sffscan.pipeline.messages.FrameHeader`, dtype, shape and the CRC-32 of the pixels,
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

Robustness: the receiver refuses messages larger than the configured frame
(:func:`max_message_bytes`, zmq's ``MAXMSGSIZE``: an oversized message drops its connection
before it is buffered); a malformed, unauthenticated or out-of-order message is refused,
logged and counted (:class:`ReceiverStats`), and the scan fails only once more than
``source.max_bad_messages`` were refused. A sender silent for ``source.idle_timeout_s``
after its first frame ends the stream without a count: the scan ends ``incomplete``.

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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
import zmq
from pydantic import BaseModel, ConfigDict, Field, RootModel, ValidationError
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.pipeline.formats.transport_auth import (
    auth_tag,
    keys_dir_of,
    load_pair,
    load_public,
    read_pairing,
    remove_pairing,
    write_pairing,
)
from sffscan.pipeline.messages import Frame, FrameHeader

if TYPE_CHECKING:
    from sffscan.pipeline.completeness import FrameAccount

logger = logging.getLogger(__name__)

DEFAULT_ADDRESS = "tcp://127.0.0.1:5555"
_WAIT_MS = 250  # longest single wait before the stop flag / timeout is checked again
#: largest header part accepted, bytes
MAX_HEADER_BYTES = 64 * 1024


class TransportError(RuntimeError):
    """A message that cannot be used, or a peer that went silent; names the frame."""


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

    With ``secret`` the second part must be the header's tag (:func:`auth_tag`); without
    it (CURVE) the second part is ignored. Raises :class:`TransportError` naming the frame
    for anything else."""
    if len(parts) not in (2, 3):
        raise TransportError(f"{len(parts)} message parts, expected 2 (end) or 3 (frame)")
    head = _buffer(parts[0])
    if head.nbytes > MAX_HEADER_BYTES:
        raise TransportError(f"header of {head.nbytes} bytes, more than {MAX_HEADER_BYTES}")
    head_bytes = bytes(head)
    if secret is not None and not hmac.compare_digest(bytes(_buffer(parts[1])),
                                                      auth_tag(secret, head_bytes)):
        raise TransportError("message not authenticated: its tag does not match this scan's "
                             "secret (not the paired sender)")
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
        self.bytes += img.nbytes

    def end(self, reason: str = "complete", *, timeout_s: float | None = 10.0) -> None:
        """Send the end-of-stream message (waiting at most ``timeout_s`` for room)."""
        head = EndMessage(frames_sent=self.sent, reason=reason[:4096]).model_dump_json().encode()
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


# --- receiver -----------------------------------------------------------------------------


@dataclass
class ReceiverStats:
    frames: int = 0
    bytes: int = 0
    ended: bool = False
    frames_sent: int | None = None
    lost: int = 0  # frames the end message says were sent that never arrived here
    rejected: int = 0  # messages refused: malformed, unauthenticated, out of order
    dropped_connections: int = 0  # peers cut off: oversized message, failed handshake
    silent: bool = False  # the stream ended because the sender went silent


_DROP_EVENTS = (zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
                | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH)


class _Receiver:
    """The PULL socket of :func:`receive_frames`, its authentication and its monitor."""

    def __init__(self, address: str, cfg: ScanConfig, hwm: int, secret: bytes | None,
                 keys_dir: str | Path | None, curve: bool | None) -> None:
        self.address = address
        self.loopback = not curve if curve is not None else is_loopback(address)
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.PULL)
        self.sock.setsockopt(zmq.RCVHWM, hwm)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.MAXMSGSIZE, max_message_bytes(cfg))
        self.auth: Any = None
        self.own_secret = False
        self.secret: bytes | None = None
        self.monitor: zmq.Socket | None = None
        try:
            if self.loopback:
                if secret is None:
                    secret, self.own_secret = write_pairing(address), True
                self.secret = secret
            else:
                from zmq.auth.thread import ThreadAuthenticator

                folder = keys_dir_of(cfg, keys_dir)
                public, secret_key = load_pair(folder, "receiver")
                if not (folder / "authorized").is_dir():
                    raise ConfigError(f"{folder / 'authorized'}: no authorised sender keys")
                self.auth = ThreadAuthenticator(self.ctx)
                self.auth.start()
                self.auth.configure_curve(domain="*", location=str(folder / "authorized"))
                self.sock.curve_server = True
                self.sock.curve_secretkey = secret_key
                self.sock.curve_publickey = public
                logger.warning("transport: listening on %s, beyond this machine (CURVE, keys "
                               "in %s)", address, folder)
            self.monitor = self.sock.get_monitor_socket(_DROP_EVENTS)
            try:
                self.sock.bind(address)
            except zmq.ZMQError as err:
                raise ConfigError(f"{address}: cannot listen: {err}") from None
        except BaseException:
            self.close()
            raise

    def drops(self) -> int:
        n = 0
        mon = self.monitor
        while mon is not None and mon.poll(0):
            mon.recv_multipart()
            n += 1
        return n

    def close(self) -> None:
        if self.monitor is not None:
            self.sock.disable_monitor()
            self.monitor.close(linger=0)
            self.monitor = None
        self.sock.close(linger=0)
        if self.auth is not None:
            self.auth.stop()
        self.ctx.term()
        if self.own_secret and self.secret is not None:
            remove_pairing(self.address, self.secret)


def receive_frames(address: str, cfg: ScanConfig, *, hwm: int | None = None,
                   idle_timeout_s: float | None = None, first_timeout_s: float | None = None,
                   stats: ReceiverStats | None = None, account: FrameAccount | None = None,
                   secret: bytes | None = None, keys_dir: str | Path | None = None,
                   max_bad: int | None = None, curve: bool | None = None) -> Iterator[Frame]:
    """Frames sent by ``sffscan grab`` to ``address`` (bound here), until the end message.

    The receive high-water mark defaults to ``processing.queue_capacity``; ``idle_timeout_s``
    and ``max_bad`` to ``source.idle_timeout_s`` and ``source.max_bad_messages``. A loopback
    receiver writes a new pairing secret unless ``secret`` is given; beyond loopback CURVE
    keys come from ``keys_dir`` (default ``source.keys_dir``); ``curve`` forces CURVE on or
    off. The end message's count goes to ``account.sent``.

    Raises :class:`TransportError` for an end message saying the sender failed, for no
    message at all within ``first_timeout_s`` (None waits indefinitely), and once more
    than ``max_bad`` messages were refused. A sender silent for ``idle_timeout_s`` after its
    first frame ends the stream (``stats.silent``; no count: the scan is incomplete). The
    socket is closed when the generator is closed, so a new receiver may bind the address
    again.
    """
    check_address(address)
    st = stats if stats is not None else ReceiverStats()
    idle = idle_timeout_s if idle_timeout_s is not None else cfg.source.idle_timeout_s
    limit_bad = max_bad if max_bad is not None else cfg.source.max_bad_messages
    rx = _Receiver(address, cfg, hwm if hwm is not None else cfg.processing.queue_capacity,
                   secret, keys_dir, curve)
    last_id = -1

    def refuse(why: str) -> None:
        st.rejected += 1
        logger.warning("transport: message %d refused: %s", st.rejected, why)
        if st.rejected > limit_bad:
            raise TransportError(f"{st.rejected} messages refused at {address}, more than "
                                 f"source.max_bad_messages = {limit_bad}; last: {why}")

    try:
        last = time.monotonic()
        while True:
            ready = rx.sock.poll(_WAIT_MS)
            dropped = rx.drops()
            if dropped and not st.ended:
                st.dropped_connections += dropped
            if not ready:
                limit = idle if st.frames else first_timeout_s
                if limit is not None and time.monotonic() - last > limit:
                    if not st.frames:
                        raise TransportError(f"no message from the sender at {address} for "
                                             f"{limit:g} s; is 'sffscan grab' running?")
                    st.silent = True
                    logger.warning("transport: no message from the sender at %s for %g s "
                                   "after %d frames and no end message: the stream ends "
                                   "here, incomplete", address, limit, st.frames)
                    return
                continue
            parts = rx.sock.recv_multipart(copy=False)
            try:
                item = decode_message(parts, secret=rx.secret)
            except TransportError as err:
                refuse(str(err))
                continue
            last = time.monotonic()
            if isinstance(item, EndMessage):
                st.ended, st.frames_sent = True, item.frames_sent
                st.lost = max(item.frames_sent - st.frames, 0)
                if st.lost:  # at a receiver restart; also after the last frame_id seen
                    logger.warning("transport: received %d of the %d frames sent: %d lost in "
                                   "transit", st.frames, item.frames_sent, st.lost)
                if item.reason != "complete":  # the scan fails, keeping what it measured
                    raise TransportError(f"the sender stopped after {item.frames_sent} "
                                         f"frames: {item.reason}")
                if account is not None:
                    account.sent = item.frames_sent
                return
            fid = item.header.frame_id
            if fid <= last_id:
                refuse(f"frame_id {fid} after frame_id {last_id}: repeated or out of order")
                continue
            last_id = fid
            st.frames += 1
            st.bytes += item.image.nbytes
            yield item
    finally:
        rx.close()
        if st.rejected or st.dropped_connections:
            logger.warning("transport: %d message(s) refused, %d connection(s) dropped at %s",
                           st.rejected, st.dropped_connections, address)


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
