"""The receiving end of the frame transport (``sffscan scan --source``); the wire format and
the sender are in :mod:`sffscan.pipeline.formats.transport`.

The receiver's plan is the truth: with a frame account, frames whose frame_id is past the
plan (``frame_id >= account.planned``) are not processed (counted, logged, named), and the
scan is ``complete`` only with every planned frame: a sender with a shorter plan, one that
ends early, ids out of range all leave it ``incomplete`` with the counts.

Refused messages: a message that fails authentication (not from the paired sender: any
local process can send one) is dropped and counted, with a warning (the first few, then
every :data:`WARN_EVERY`-th), and never stops the scan; zmq's high-water mark and
``MAXMSGSIZE`` bound the memory it can take. A message from the paired sender that cannot
be used (malformed, checksum, out of order) is refused and counted too, and the scan fails
once more than ``source.max_bad_messages`` of those were refused.

The socket is bound and the pairing file written when :func:`receive_frames` is called, not
at the first frame: an address already in use is a :class:`ConfigError` (exit 2) before
anything else happens, and the running receiver's pairing file is left alone.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zmq
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.pipeline.formats.transport import (
    _WAIT_MS,
    EndMessage,
    TransportError,
    Unauthenticated,
    check_address,
    decode_message,
    is_loopback,
    max_message_bytes,
)
from sffscan.pipeline.formats.transport_auth import (
    check_authorized_dir,
    keys_dir_of,
    load_pair,
    remove_pairing,
    write_pairing,
)
from sffscan.stages.frame_source import SourceFrames
from sffscan.stages.messages import Frame

if TYPE_CHECKING:
    from sffscan.pipeline.completeness import FrameAccount

logger = logging.getLogger(__name__)

#: unauthenticated messages: a warning for each of the first ones, then every this many
WARN_EVERY = 100
_WARN_FIRST = 5


@dataclass
class ReceiverStats:
    frames: int = 0
    bytes: int = 0
    ended: bool = False
    frames_sent: int | None = None
    lost: int = 0  # frames the end message says were sent that never arrived here
    #: planned frame_ids after the last frame received, up to the end message's last one
    #: (no later frame_id shows their gap to the scan's source stage)
    lost_at_end: int = 0
    rejected: int = 0  # messages refused: malformed, unauthenticated, out of order
    unauthenticated: int = 0  # of which not from the paired sender (dropped, never fatal)
    beyond_plan: int = 0  # frames from the sender whose frame_id is past the plan
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
        self.closed = False
        try:
            if not self.loopback:
                from zmq.auth.thread import ThreadAuthenticator

                folder = keys_dir_of(cfg, keys_dir)
                public, secret_key = load_pair(folder, "receiver")
                check_authorized_dir(folder)
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
                raise ConfigError(f"{address}: cannot listen: {err} (another receiver, "
                                  "'sffscan scan --source', may be running there; its "
                                  "pairing is left alone)") from None
            if self.loopback:  # only once the address is ours: never another receiver's
                if secret is None:
                    secret, self.own_secret = write_pairing(address), True
                self.secret = secret
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
        if self.closed:
            return
        self.closed = True
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


class FrameStream(SourceFrames):
    """The frames of a bound receiver (:func:`receive_frames`); ``close()`` releases the
    socket and the pairing file, whether or not a frame was taken."""

    def __init__(self, rx: _Receiver, frames: Iterator[Frame], stats: ReceiverStats) -> None:
        super().__init__(frames, lost_at_end=lambda: stats.lost_at_end)
        self._rx = rx

    def close(self) -> None:
        super().close()
        self._rx.close()

    def __del__(self) -> None:
        try:
            self._rx.close()
        except Exception:  # noqa: BLE001, S110 - interpreter shutdown: nothing to report to
            pass


def receive_frames(address: str, cfg: ScanConfig, *, hwm: int | None = None,
                   idle_timeout_s: float | None = None, first_timeout_s: float | None = None,
                   stats: ReceiverStats | None = None, account: FrameAccount | None = None,
                   secret: bytes | None = None, keys_dir: str | Path | None = None,
                   max_bad: int | None = None, curve: bool | None = None) -> FrameStream:
    """Frames sent by ``sffscan grab`` to ``address`` (bound now), until the end message.

    The receive high-water mark defaults to ``processing.queue_capacity``; ``idle_timeout_s``
    and ``max_bad`` to ``source.idle_timeout_s`` and ``source.max_bad_messages``. A loopback
    receiver writes a new pairing secret (once bound) unless ``secret`` is given; beyond
    loopback CURVE keys come from ``keys_dir`` (default ``source.keys_dir``); ``curve``
    forces CURVE on or off. With ``account``, frames past ``account.planned`` are not
    processed, and ``account.sent`` is the end message's count, or the plan when that is
    larger (the receiver's plan is the truth).

    Raises :class:`ConfigError` now for an address that cannot be bound (in use) or keys
    that cannot be used. The frames raise :class:`TransportError` for an end message saying
    the sender failed, for no message at all within ``first_timeout_s`` (None waits
    indefinitely), and once more than ``max_bad`` messages of the paired sender were
    refused (unauthenticated ones are dropped and counted, never fatal). A sender silent for
    ``idle_timeout_s`` after its first frame ends the stream (``stats.silent``; no count:
    the scan is incomplete). Closing the stream closes the socket, so a new receiver may
    bind the address again.
    """
    check_address(address)
    st = stats if stats is not None else ReceiverStats()
    rx = _Receiver(address, cfg, hwm if hwm is not None else cfg.processing.queue_capacity,
                   secret, keys_dir, curve)
    idle = idle_timeout_s if idle_timeout_s is not None else cfg.source.idle_timeout_s
    limit_bad = max_bad if max_bad is not None else cfg.source.max_bad_messages
    return FrameStream(rx, _frames(rx, st, idle, first_timeout_s, limit_bad, account), st)


def _frames(rx: _Receiver, st: ReceiverStats, idle: float, first_timeout_s: float | None,
            limit_bad: int, account: FrameAccount | None) -> Iterator[Frame]:
    address = rx.address
    plan = account.planned if account is not None else None
    last_id = -1

    def refuse(why: str, *, authenticated: bool) -> None:
        st.rejected += 1
        if not authenticated:
            st.unauthenticated += 1
            n = st.unauthenticated
            if n <= _WARN_FIRST or n % WARN_EVERY == 0:
                logger.warning("transport: %d unauthenticated message(s) dropped at %s (not "
                               "from the paired sender; the scan goes on); last: %s", n,
                               address, why)
            return
        bad = st.rejected - st.unauthenticated
        logger.warning("transport: message %d of the paired sender refused: %s", bad, why)
        if bad > limit_bad:
            raise TransportError(f"{bad} messages of the paired sender refused at {address}, "
                                 f"more than source.max_bad_messages = {limit_bad}; last: "
                                 f"{why}")

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
            except Unauthenticated as err:
                refuse(str(err), authenticated=False)
                continue
            except TransportError as err:
                refuse(str(err), authenticated=True)
                continue
            last = time.monotonic()
            if isinstance(item, EndMessage):
                _end(item, st, account, plan, last_id)
                return
            fid = item.header.frame_id
            if fid <= last_id:
                refuse(f"frame_id {fid} after frame_id {last_id}: repeated or out of order",
                       authenticated=True)
                continue
            if plan is not None and fid >= plan:
                st.beyond_plan += 1
                if st.beyond_plan <= _WARN_FIRST or st.beyond_plan % WARN_EVERY == 0:
                    logger.warning("transport: frame_id %d is past the receiver's plan of %d "
                                   "frames (frame_id 0..%d): not processed (%d so far); the "
                                   "scan will be incomplete", fid, plan, plan - 1,
                                   st.beyond_plan)
                last_id = fid
                continue
            last_id = fid
            st.frames += 1
            st.bytes += item.image.nbytes
            yield item
    finally:
        rx.close()
        if st.rejected or st.dropped_connections or st.beyond_plan:
            logger.warning("transport: %d message(s) refused (%d unauthenticated), %d "
                           "frame(s) past the plan, %d connection(s) dropped at %s",
                           st.rejected, st.unauthenticated, st.beyond_plan,
                           st.dropped_connections, address)


def _end(item: EndMessage, st: ReceiverStats, account: FrameAccount | None,
         plan: int | None, last_id: int) -> None:
    """The end message: counts, and the account's expected count (never below the plan).
    ``last_id``: the frame_id of the last frame received within the plan (-1: none)."""
    st.ended, st.frames_sent = True, item.frames_sent
    st.lost = max(item.frames_sent - st.frames - st.beyond_plan, 0)
    if item.last_frame_id is not None and plan is not None:
        # the sender's frame_ids past the last one received, within the plan (a sender
        # claiming more cannot push the count past the plan)
        st.lost_at_end = max(min(item.last_frame_id, plan - 1) - last_id, 0)
    if st.lost:  # at a receiver restart; also after the last frame_id seen
        logger.warning("transport: received %d of the %d frames sent: %d lost in "
                       "transit", st.frames, item.frames_sent, st.lost)
    if item.reason != "complete":  # the scan fails, keeping what it measured
        raise TransportError(f"the sender stopped after {item.frames_sent} "
                             f"frames: {item.reason}")
    if plan is not None and item.frames_sent < plan:
        logger.warning("transport: the sender ended after %d frames, the receiver's plan "
                       "has %d: the scan is incomplete", item.frames_sent, plan)
    if account is not None:
        account.sent = max(item.frames_sent, plan) if plan is not None else item.frames_sent
