"""zmq frame transport (pipeline.formats.transport, `sffscan grab`): two processes on loopback."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zarr
import zmq
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ScanConfig, config_from_dict, config_to_toml
from sffscan.pipeline.formats.transport import (
    EndMessage,
    FrameSender,
    TransportError,
    decode_message,
    encode_frame,
    stream_frames,
)
from sffscan.pipeline.formats.transport_receiver import ReceiverStats, receive_frames
from sffscan.pipeline.plan import frame_count
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame, FrameHeader

ROOT = Path(__file__).resolve().parents[3]


def tiny_config(**output: object) -> ScanConfig:
    """160 x 64 px of 17 µm, N = 10, 150 fps, 15 mm/s over 8 mm: about 100 frames."""
    return config_from_dict({
        "source": {"world": "plate", "plate_length_mm": 12.0, "plate_width_mm": 2.0},
        "optics": {"width_px": 160, "height_px": 64, "pixel_um": 17.0, "n_levels": 10},
        "motion": {"x_start_mm": 1.0, "x_end_mm": 9.0},
        "processing": {"block_columns": 32, "registration_scale": 2},
        "output": {"chunk_px": 64, **output},
    }, origin="test")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_grab(cfg: ScanConfig, tmp: Path, address: str, *extra: str) -> subprocess.Popen:
    path = tmp / "grab.toml"
    path.write_text(config_to_toml(cfg), encoding="utf-8")
    return subprocess.Popen([sys.executable, "-m", "sffscan", "grab", "--config",
                             str(path), "--to", address, *extra], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen) -> tuple[int, str]:
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, err


def test_two_processes_every_frame_arrives_intact(tmp_path: Path) -> None:
    cfg = tiny_config()
    address = f"tcp://127.0.0.1:{free_port()}"
    expected = {f.header.frame_id: f for f in simulate_frames(cfg)}
    st = ReceiverStats()
    gen = receive_frames(address, cfg, first_timeout_s=60, stats=st)
    proc = start_grab(cfg, tmp_path, address)
    try:
        got = list(gen)
    finally:
        rc, err = finish(proc)
    assert rc == 0, err
    assert len(got) == len(expected) == frame_count(cfg) == st.frames_sent
    assert st.ended
    for frame in got:  # the CRC was checked on receipt; compare every pixel too
        exp = expected[frame.header.frame_id]
        assert frame.header == exp.header
        assert frame.image.dtype == exp.image.dtype
        assert zlib.crc32(frame.image.data) == zlib.crc32(exp.image.data)
        np.testing.assert_array_equal(frame.image, exp.image)
    assert f"sent {len(got)} frames" in err


def test_receiver_stopped_and_restarted(tmp_path: Path) -> None:
    """The receiver closes after 20 frames and binds again: the sender reconnects by itself;
    frames in flight at the close may be lost (a frame_id gap), none is corrupted."""
    cfg = tiny_config()
    address = f"tcp://127.0.0.1:{free_port()}"
    expected = {f.header.frame_id: f.image for f in simulate_frames(cfg)}
    first = receive_frames(address, cfg, hwm=2, first_timeout_s=60)
    proc = start_grab(cfg, tmp_path, address, "--hwm", "2")
    try:
        got = [next(first) for _ in range(20)]
        # the receiver stops: socket closed, messages queued for it dropped
        first.close()  # type: ignore[attr-defined]
        time.sleep(0.3)
        st = ReceiverStats()
        got2 = list(receive_frames(address, cfg, hwm=2, first_timeout_s=60, stats=st))
    finally:
        rc, err = finish(proc)
    assert rc == 0, err
    assert len(got2) > 0 and st.ended and st.frames_sent == frame_count(cfg)
    ids = [f.header.frame_id for f in got + got2]
    print(f"restart: first session {len(got)} frames, second {len(got2)} from frame_id "
          f"{got2[0].header.frame_id}; lost at the restart {frame_count(cfg) - len(ids)}")
    assert ids == sorted(set(ids))  # strictly increasing: nothing repeated or reordered
    assert ids[-1] == frame_count(cfg) - 1  # the last frame arrived after the restart
    for frame in got + got2:
        np.testing.assert_array_equal(frame.image, expected[frame.header.frame_id])


def test_scan_from_grab_equals_the_direct_scan(tmp_path: Path) -> None:
    """`sffscan scan --source tcp://...` fed by `sffscan grab` in another process writes the
    same mosaic as the scan of the same simulated frames in process."""
    cfg = tiny_config(path=str(tmp_path / "direct.zarr"))
    assert main(["scan", "--config", _toml(cfg, tmp_path / "scan.toml"), "-q",
                 "--no-evaluate"]) == 0
    address = f"tcp://127.0.0.1:{free_port()}"
    proc = start_grab(cfg, tmp_path, address)
    try:
        rc = main(["scan", "--config", str(tmp_path / "scan.toml"), "-q", "--no-evaluate",
                   "--source", address, "-o", str(tmp_path / "tcp.zarr")])
    finally:
        grab_rc, err = finish(proc)
    assert rc == 0 and grab_rc == 0, err
    a = zarr.open_group(str(tmp_path / "direct.zarr"), mode="r")
    b = zarr.open_group(str(tmp_path / "tcp.zarr"), mode="r")
    assert b.attrs["status"] == "complete"
    ha, hb = np.asarray(a["height"]), np.asarray(b["height"])  # type: ignore[index]
    assert np.isfinite(hb).sum() > 1000
    np.testing.assert_array_equal(ha, hb)


def _toml(cfg: ScanConfig, path: Path) -> str:
    path.write_text(config_to_toml(cfg), encoding="utf-8")
    return str(path)


def _frame(fid: int = 3) -> Frame:
    img = (np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * 5) % 1024
    return Frame(FrameHeader(frame_id=fid, timestamp_ns=10, focus_index=1), img)


def test_header_is_json_validated_and_pixels_are_raw() -> None:
    head, img = encode_frame(_frame())
    meta = json.loads(head)  # plain JSON, never pickle
    assert meta["kind"] == "frame" and meta["dtype"] == "uint16" and meta["shape"] == [12, 16]
    assert meta["header"]["frame_id"] == 3 and meta["crc32"] == zlib.crc32(img.data)
    out = decode_message([head, b"", img.tobytes()])
    assert isinstance(out, Frame)
    np.testing.assert_array_equal(out.image, img)
    end = decode_message([EndMessage(frames_sent=4).model_dump_json().encode(), b""])
    assert isinstance(end, EndMessage) and end.frames_sent == 4


def test_bad_messages_are_refused_naming_the_frame() -> None:
    head, img = encode_frame(_frame(7))
    bad = bytearray(img.tobytes())
    bad[5] ^= 0xFF
    with pytest.raises(TransportError, match="frame_id 7: pixel checksum mismatch"):
        decode_message([head, b"", bytes(bad)])
    with pytest.raises(TransportError, match="frame_id 7: 382 bytes"):
        decode_message([head, b"", img.tobytes()[:-2]])
    with pytest.raises(TransportError, match="frame_id 7: 2 message parts"):
        decode_message([head, b""])
    with pytest.raises(TransportError, match="1 message parts"):
        decode_message([head])
    meta = json.loads(head)
    meta["header"]["frame_id"] = -1
    with pytest.raises(TransportError, match="transport schema.*header.frame_id"):
        decode_message([json.dumps(meta).encode(), b"", img.tobytes()])
    with pytest.raises(TransportError, match="transport schema"):
        decode_message([b"\x80\x04pickle", b"", img.tobytes()])


def test_sender_takes_the_buffer_over() -> None:
    """zmq may read a sent buffer after send returns: the sender makes it read-only, so a
    source cannot reuse it for the next frame."""
    port = free_port()
    frame = _frame()
    frame.image = np.ascontiguousarray(frame.image)
    sender = FrameSender(f"tcp://127.0.0.1:{port}", hwm=4, secret=b"k" * 32)
    try:
        assert sender._sock.getsockopt(zmq.CONFLATE) == 0  # it breaks multipart messages
        sender.send(frame)  # queued (no receiver): zero copy, zmq holds the buffer
        assert not frame.image.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            frame.image[0, 0] = 1
        with pytest.raises(TransportError, match="took no message"):
            for _ in range(10):  # fill the high-water marks, then time out
                sender._send(b"x", [], timeout_s=0.3)
    finally:
        sender.close(linger_s=0)


def test_addresses_are_checked(tmp_path: Path) -> None:
    cfg = tiny_config()
    with pytest.raises(Exception, match="expected a zmq address"):
        next(receive_frames("udp://1.2.3.4:5", cfg))
    assert main(["scan", "--config", _toml(cfg, tmp_path / "c.toml"), "--source",
                 "http://x"]) == 2


def test_a_failed_sender_fails_the_receiver() -> None:
    """An end message with a failure reason (the camera stopped) raises, so the scan exits 1
    with the mosaic kept, instead of finishing as if the scan were complete."""
    address = f"tcp://127.0.0.1:{free_port()}"
    cfg = tiny_config()
    gen = receive_frames(address, cfg, first_timeout_s=30)

    def broken() -> Iterator[Frame]:
        yield _frame(0)
        yield _frame(1)
        raise RuntimeError("camera unplugged")

    def send() -> None:
        sender = FrameSender(address)
        try:
            with pytest.raises(RuntimeError):
                stream_frames(broken(), sender)
        finally:
            sender.close()

    thread = threading.Thread(target=send)
    thread.start()
    got = []
    with pytest.raises(TransportError, match="sender stopped after 2 frames: RuntimeError: "
                                             "camera unplugged"):
        for frame in gen:
            got.append(frame.header.frame_id)
    thread.join(30)
    assert got == [0, 1]


def test_frames_lost_in_transit_are_reported_at_the_end(
        caplog: pytest.LogCaptureFixture) -> None:
    """The end message says 4 frames were sent; 2 arrived (the others were lost at a
    receiver restart, here after the last one received, where no frame_id gap shows them):
    the receiver counts and says so instead of ending as if nothing were missing."""
    address = f"tcp://127.0.0.1:{free_port()}"
    st = ReceiverStats()
    gen = receive_frames(address, tiny_config(), first_timeout_s=30, stats=st)
    got: list[int] = []

    def send() -> None:
        sender = FrameSender(address)
        try:
            sender.send(_frame(0))
            sender.send(_frame(1))
            sender.sent = 4  # frames 2 and 3 went to a receiver that was stopped
            sender.end()
        finally:
            sender.close()

    thread = threading.Thread(target=send)
    thread.start()
    got = [f.header.frame_id for f in gen]
    thread.join(30)
    assert got == [0, 1] and st.ended and st.frames_sent == 4
    assert st.lost == 2
    assert "received 2 of the 4 frames sent: 2 lost in transit" in caplog.text


def test_frames_lost_after_the_last_one_received_reach_the_source_stage() -> None:
    """Frames 0-2 and 4 arrive; 3 and 5 were sent and lost. No later frame_id shows frame
    5's gap: the end message's last frame_id does, so the scan's source stage counts both
    (a frame_id gap mid-stream, the tail from the stream), as a camera's tail losses."""
    from sffscan.pipeline.completeness import FrameAccount
    from sffscan.stages.frame_source import SourceStage

    address = f"tcp://127.0.0.1:{free_port()}"
    st = ReceiverStats()
    frames = receive_frames(address, tiny_config(), first_timeout_s=30, stats=st,
                            account=FrameAccount(planned=6))
    img = (np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * 5) % 1024

    def send() -> None:
        sender = FrameSender(address)
        try:
            for fid in (0, 1, 2, 4):
                sender.send(Frame(FrameHeader(frame_id=fid, timestamp_ns=10 * fid,
                                              focus_index=fid % 10), img.copy()))
            sender.sent, sender.last_frame_id = 6, 5  # 3 and 5 never arrived
            sender.end()
        finally:
            sender.close()

    thread = threading.Thread(target=send)
    thread.start()
    src = SourceStage(frames, shape=(12, 16), dtype="uint16", n_levels=10, max_value=1023,
                      passes=1, area_um=(0.0, 0.0, 1e9, 1e9))
    got = [f.header.frame_id for f in src.produce()]
    thread.join(30)
    assert got == [0, 1, 2, 4] and (st.lost, st.lost_at_end) == (2, 1)
    assert src.extra_stats() == {"frame_id_gaps": 2, "frames_lost": 2}


def test_a_sender_cannot_claim_tail_losses_past_the_plan() -> None:
    """An end message's last frame_id far past the plan counts only the plan's frames."""
    from sffscan.pipeline.completeness import FrameAccount
    from sffscan.pipeline.formats.transport_receiver import _end

    st = ReceiverStats(frames=2)
    end = EndMessage(frames_sent=2, last_frame_id=2**63 - 1)
    _end(end, st, FrameAccount(planned=6), 6, 1)
    assert st.lost_at_end == 4
    st = ReceiverStats(frames=2)
    _end(EndMessage(frames_sent=2), st, FrameAccount(planned=6), 6, 1)  # an older sender
    assert st.lost_at_end == 0


def test_a_negative_shape_is_refused_naming_the_frame() -> None:
    """(-12, -16) has the same byte count as (12, 16): refused as a bad header, not a
    numpy ValueError that names nothing."""
    head, img = encode_frame(_frame(9))
    meta = json.loads(head)
    meta["shape"] = [-12, -16]
    with pytest.raises(TransportError, match="frame_id 9: shape"):
        decode_message([json.dumps(meta).encode(), b"", img.tobytes()])


def test_the_checksum_catches_a_buffer_reused_before_zmq_sent_it() -> None:
    """What FrameSender.send's read-only flag prevents: a queued zero-copy frame (128 kB,
    above pyzmq's copy threshold) whose array is overwritten before the receiver is there
    arrives with other pixels than its CRC-32 says; the receiver refuses it."""
    address = f"tcp://127.0.0.1:{free_port()}"
    img = np.arange(256 * 256, dtype=np.uint16).reshape(256, 256)
    head, out = encode_frame(Frame(FrameHeader(frame_id=5, timestamp_ns=0, focus_index=5),
                                   img))
    assert out is img and img.nbytes > zmq.COPY_THRESHOLD
    key = b"s" * 32
    sender = FrameSender(address, secret=key)
    try:
        sender._send(head, [out])  # bypasses send(): the array stays writable
        img[:] = 7  # a source reusing its buffer for the next frame
        cfg = config_from_dict({"optics": {"width_px": 256, "height_px": 256, "pixel_um": 17.0,
                                           "n_levels": 10}})  # 256 x 256 px messages fit
        gen = receive_frames(address, cfg, first_timeout_s=30, secret=key, max_bad=0)
        with pytest.raises(TransportError, match="frame_id 5: pixel checksum mismatch"):
            next(gen)
    finally:
        sender.close(linger_s=0)
