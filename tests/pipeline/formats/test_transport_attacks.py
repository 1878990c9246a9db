"""The transport attacked (issue 23): the receiver's plan is the truth (defect 6), ids out of
range (18), loose key and pairing permissions (10, 11), junk messages (12), a second receiver
on a busy address (13), ``localhost`` against ``127.0.0.1`` (14); property-based wire
headers."""

from __future__ import annotations

import functools
import json
import logging
import os
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest
import zarr
import zmq
from hypothesis import example, given, settings
from hypothesis import strategies as st
from sffscan.pipeline.cli.common import EXIT_INCOMPLETE
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.completeness import FrameAccount
from sffscan.pipeline.config import ConfigError, config_to_toml
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.formats.transport import (
    EndMessage,
    FrameSender,
    TransportError,
    decode_message,
    encode_frame,
)
from sffscan.pipeline.formats.transport_auth import (
    auth_tag,
    load_pair,
    make_keys,
    pairing_path,
    read_pairing,
)
from sffscan.pipeline.formats.transport_receiver import ReceiverStats, receive_frames
from sffscan.pipeline.plan import frame_count
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame, FrameHeader

from tests.pipeline.formats.test_transport import finish, free_port, start_grab, tiny_config

SECRET = b"s" * 32


@functools.cache
def _simulated() -> tuple[Frame, ...]:
    return tuple(f for _, f in zip(range(12), simulate_frames(tiny_config()), strict=False))


def _frames(n: int) -> list[Frame]:
    """The first ``n`` (up to 12) simulated frames, each image a fresh copy (a sender takes
    its frames over)."""
    return [Frame(f.header, f.image.copy()) for f in _simulated()[:n]]


def _receive(address: str, account: FrameAccount, send: list[Frame], *,
             stats: ReceiverStats | None = None) -> list[Frame]:
    """Receive what a paired sender (in a thread) sends: ``send`` then the end message."""
    gen = receive_frames(address, tiny_config(), first_timeout_s=30, secret=SECRET,
                         account=account, stats=stats)

    def run() -> None:
        with FrameSender(address, secret=SECRET) as sender:
            for f in send:
                sender.send(Frame(f.header, f.image.copy()))
            sender.end()

    t = threading.Thread(target=run)
    t.start()
    try:
        return list(gen)
    finally:
        t.join(30)
        gen.close()


def test_ids_past_the_plan_are_not_processed_and_the_scan_is_incomplete() -> None:
    """Defect 6: ids jumping to 2**62 made the scan 'complete' with 2**62 frames lost."""
    frames = _frames(10)
    jump = [Frame(f.header.model_copy(update={"frame_id": 2**62 + i}), f.image)
            for i, f in enumerate(frames[:5])]
    account = FrameAccount(planned=10, needs_sender=True)
    st_ = ReceiverStats()
    got = _receive(f"tcp://127.0.0.1:{free_port()}", account, frames[:6] + jump, stats=st_)
    account.received = len(got)
    assert [f.header.frame_id for f in got] == list(range(6))
    assert st_.beyond_plan == 5 and st_.lost == 0
    assert not account.complete and account.expected == 11


def test_a_sender_that_ends_early_leaves_the_scan_incomplete() -> None:
    account = FrameAccount(planned=10, needs_sender=True)
    got = _receive(f"tcp://127.0.0.1:{free_port()}", account, _frames(4))
    account.received = len(got)
    assert len(got) == 4 and account.expected == 10 and not account.complete
    assert account.describe() == "4 of 10 expected frames received and processed, 6 missing"


def test_a_grab_of_a_shorter_plan_is_incomplete(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Defect 6: a paired grab of a shorter plan ended 'complete 45/45'."""
    cfg = tiny_config(path=str(tmp_path / "m.zarr"))
    short = tiny_config()
    data = short.model_dump()
    data["motion"]["x_end_mm"] = 5.0
    short = type(cfg).model_validate(data)
    assert frame_count(short) < frame_count(cfg)
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    address = f"tcp://127.0.0.1:{free_port()}"
    proc = start_grab(short, tmp_path, address)
    try:
        rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address])
    finally:
        grab_rc, err = finish(proc)
    assert grab_rc == 0, err
    assert rc == EXIT_INCOMPLETE, capsys.readouterr().err
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs.asdict()
    assert attrs["status"] == "incomplete"
    assert attrs["frames_expected"] == frame_count(cfg)
    assert attrs["frames_received"] == frame_count(short)


def _raw(header: dict[str, object], image: np.ndarray, secret: bytes | None = SECRET
         ) -> list[bytes]:
    head = json.dumps({"kind": "frame", "dtype": image.dtype.name, "shape": list(image.shape),
                       "crc32": zlib.crc32(image.data), "header": header}).encode()
    return [head, auth_tag(secret, head) if secret else b"", image.tobytes()]


@pytest.mark.parametrize(("field", "value"), [("frame_id", 2**63), ("frame_id", 2**64 + 5),
                                              ("timestamp_ns", 2**63),
                                              ("focus_index", 2**31)])
def test_ids_out_of_range_are_refused_naming_the_field(field: str, value: int) -> None:
    """Defect 18: an OverflowError from the recorder named neither the frame nor the field."""
    header: dict[str, object] = {"frame_id": 7, "timestamp_ns": 1, "focus_index": 0,
                                 field: value}
    with pytest.raises(TransportError, match=f"header.{field}"):
        decode_message(_raw(header, np.zeros((4, 5), np.uint16)), secret=SECRET)


def test_the_recorder_names_a_field_out_of_range(tmp_path: Path) -> None:
    cfg = tiny_config()
    frame = _frames(1)[0]
    bad = FrameHeader.model_construct(frame_id=2**63, timestamp_ns=0, focus_index=0,
                                      stage_x_um=None, stage_y_um=None, pass_index=0)
    w = RecordingWriter(tmp_path / "r.zarr", cfg)
    with pytest.raises(ValueError, match=r"frame_id 9223372036854775808: field frame_id"):
        w.write(Frame(bad, frame.image))
    w.close()


class _Count(logging.Handler):
    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n
        self.reached = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if "unauthenticated" in record.getMessage() and record.args \
                and record.args[0] == self.n:  # type: ignore[index]
            self.reached.set()


def test_junk_messages_never_stop_the_scan() -> None:
    """Defect 12: 101 unauthenticated messages aborted a running scan."""
    address = f"tcp://127.0.0.1:{free_port()}"
    count = _Count(200)
    log = logging.getLogger("sffscan.pipeline.formats.transport_receiver")
    log.addHandler(count)
    account = FrameAccount(planned=5, needs_sender=True)
    stats = ReceiverStats()
    gen = receive_frames(address, tiny_config(), first_timeout_s=30, secret=SECRET,
                         account=account, stats=stats)
    frames = _frames(5)

    def junk() -> None:
        ctx = zmq.Context()
        s = ctx.socket(zmq.PUSH)
        s.connect(address)
        for i in range(200):
            s.send_multipart([b"junk %d" % i] * (1 + i % 3))
        s.close(linger=30_000)
        ctx.term()

    def paired() -> None:
        with FrameSender(address, secret=SECRET) as sender:
            for f in frames:
                sender.send(Frame(f.header, f.image.copy()))
            count.reached.wait(60)  # the end only once the junk is all counted
            sender.end()

    threads = [threading.Thread(target=junk), threading.Thread(target=paired)]
    for t in threads:
        t.start()
    try:
        got = list(gen)
    finally:
        for t in threads:
            t.join(60)
        log.removeHandler(count)
        gen.close()
    assert [f.header.frame_id for f in got] == list(range(5))
    assert stats.unauthenticated == 200 and stats.rejected == 200
    assert account.sent == 5


def test_a_second_receiver_leaves_the_first_ones_pairing_alone(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Defect 13: the second receiver overwrote, then deleted the first one's pairing file,
    and its scan exited 1."""
    address = f"tcp://127.0.0.1:{free_port()}"
    first = receive_frames(address, tiny_config(), first_timeout_s=30)
    try:
        secret = read_pairing(address)
        assert secret is not None
        with pytest.raises(ConfigError, match="cannot listen"):
            second = receive_frames(address, tiny_config(), first_timeout_s=1)
            next(second)
        assert read_pairing(address) == secret
        cfg = tiny_config(path=str(tmp_path / "keep.zarr"))
        toml = tmp_path / "scan.toml"
        toml.write_text(config_to_toml(cfg), encoding="utf-8")
        rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address])
        assert rc == 2
        assert address in capsys.readouterr().err
        assert not (tmp_path / "keep.zarr").exists()
        assert read_pairing(address) == secret
    finally:
        first.close()
    assert not pairing_path(address).exists()


def test_localhost_and_127_0_0_1_name_the_same_pairing() -> None:
    """Defect 14: ``grab --to tcp://localhost:P`` waited forever for a receiver on
    ``tcp://127.0.0.1:P``."""
    port = free_port()
    assert pairing_path(f"tcp://localhost:{port}") == pairing_path(f"tcp://127.0.0.1:{port}")
    assert pairing_path("tcp://127.0.0.1:5555") != pairing_path("tcp://127.0.0.1:5556")
    account = FrameAccount(planned=3, needs_sender=True)
    gen = receive_frames(f"tcp://127.0.0.1:{port}", tiny_config(), first_timeout_s=30,
                         account=account)
    frames = _frames(3)

    def run() -> None:
        with FrameSender(f"tcp://localhost:{port}") as sender:  # reads the pairing file
            for f in frames:
                sender.send(Frame(f.header, f.image.copy()))
            sender.end()

    t = threading.Thread(target=run)
    t.start()
    try:
        got = list(gen)
    finally:
        t.join(30)
        gen.close()
    assert len(got) == 3 and account.sent == 3


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    folder = tmp_path / "keys"
    make_keys(folder)
    return folder


@pytest.mark.parametrize(("target", "mode", "named"), [
    ("", 0o777, ""), ("", 0o775, ""), ("receiver.key_secret", 0o666, "receiver.key_secret"),
    ("receiver.key_secret", 0o644, "receiver.key_secret"),
    ("authorized", 0o777, "authorized")])
def test_loose_key_permissions_are_refused_naming_the_path(
        keys: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], target: str,
        mode: int, named: str) -> None:
    """Defect 10: key folders and secret key files of mode 777/666 were used without a word
    (``--check``, the CURVE receiver, ``grab --keys``)."""
    path = keys / target if target else keys
    path.chmod(mode)
    cfg = tiny_config(path=str(tmp_path / "m.zarr"))
    data = cfg.model_dump()
    data["source"]["keys_dir"] = str(keys)
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(type(cfg).model_validate(data)), encoding="utf-8")
    address = f"tcp://127.0.0.1:{free_port()}"
    if target != "authorized":  # --check checks the receiver's pair and folder
        assert main(["scan", "--config", str(toml), "--check", "--source",
                     "tcp://0.0.0.0:5599"]) == 2
        err = capsys.readouterr().err
        assert f"{path}: mode {mode:04o}" in err, err
    with pytest.raises(ConfigError, match=f"{path}: mode {mode:04o}"):
        receive_frames(address, tiny_config(), keys_dir=keys, curve=True)
    assert not (tmp_path / "m.zarr").exists()
    if target == "receiver.key_secret":
        (keys / "sender.key_secret").chmod(mode)
        path = keys / "sender.key_secret"
    if target != "authorized":  # the sender's side: grab --keys
        with pytest.raises(ConfigError, match=f"{path}: mode {mode:04o}"):
            FrameSender(address, keys_dir=keys, curve=True)
        with pytest.raises(ConfigError, match=f"{path}: mode {mode:04o}"):
            load_pair(keys, "sender")


def test_grab_refuses_a_pairing_folder_others_can_write(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Defect 11: grab trusted a pairing file in a folder any local user can write."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    address = f"tcp://127.0.0.1:{free_port()}"
    path = pairing_path(address)
    path.parent.mkdir(mode=0o700)
    path.write_text(os.urandom(32).hex())
    path.chmod(0o600)
    assert read_pairing(address) is not None
    path.parent.chmod(0o777)
    with pytest.raises(ConfigError, match=f"{path.parent}: mode 0777"):
        read_pairing(address)
    with pytest.raises(ConfigError, match=f"{path.parent}: mode 0777"):
        FrameSender(address)
    path.parent.chmod(0o700)
    path.chmod(0o644)
    with pytest.raises(ConfigError, match=f"{path}: mode 0644"):
        read_pairing(address)


headers = st.fixed_dictionaries({
    "frame_id": st.integers(-2, 2**65), "timestamp_ns": st.integers(-2, 2**65),
    "focus_index": st.integers(-2, 2**33), "pass_index": st.integers(-2, 2**33),
    "stage_x_um": st.none() | st.floats() | st.text(max_size=3)})


@settings(max_examples=80, deadline=None)
@given(header=headers, kind=st.sampled_from(["frame", "end", "bogus"]),
       shape=st.tuples(st.integers(-1, 6), st.integers(-1, 6)),
       dtype=st.sampled_from(["uint8", "uint16", "float64"]), tagged=st.booleans())
@example(header={"frame_id": 0, "timestamp_ns": 0, "focus_index": 0, "pass_index": 0,
                 "stage_x_um": None}, kind="frame", shape=(6, 5), dtype="uint16", tagged=True)
def test_any_wire_header_is_decoded_or_refused_never_crashes(
        header: dict[str, object], kind: str, shape: tuple[int, int], dtype: str,
        tagged: bool) -> None:
    """Whatever the header holds, decode_message returns a frame whose header is in range,
    or raises TransportError; a frame that is accepted holds the bytes sent, in the shape
    and dtype its (authenticated) header declares: (6, 5) uint16 is as valid a reading of
    the 60 bytes as the (5, 6) they were sent as."""
    image = np.arange(30, dtype=np.uint16).reshape(5, 6)
    if kind == "end":
        body: dict[str, object] = {"kind": "end", "frames_sent": header["frame_id"]}
        parts = [json.dumps(body).encode()]
        parts.append(auth_tag(SECRET, parts[0]) if tagged else b"x")
    else:
        parts = _raw(header, image, SECRET if tagged else None)
        doc = json.loads(parts[0])
        doc.update(kind=kind, shape=list(shape), dtype=dtype)
        parts[0] = json.dumps(doc).encode()
        if tagged:
            parts[1] = auth_tag(SECRET, parts[0])
    try:
        item = decode_message(parts, secret=SECRET)
    except TransportError:
        return
    assert tagged
    if isinstance(item, EndMessage):
        assert 0 <= item.frames_sent <= 2**53
        return
    h = item.header
    assert 0 <= h.frame_id < 2**63 and 0 <= h.timestamp_ns < 2**63
    assert 0 <= h.focus_index < 2**31 and 0 <= h.pass_index < 2**31
    assert kind == "frame" and item.image.shape == shape
    assert item.image.dtype == np.dtype(dtype)
    assert item.image.tobytes() == image.tobytes()


@settings(max_examples=40, deadline=None)
@given(fid=st.integers(0, 2**63 - 1), ts=st.integers(0, 2**63 - 1),
       focus=st.integers(0, 2**31 - 1))
def test_valid_headers_round_trip_on_the_wire(fid: int, ts: int, focus: int) -> None:
    frame = Frame(FrameHeader(frame_id=fid, timestamp_ns=ts, focus_index=focus),
                  np.arange(12, dtype=np.uint8).reshape(3, 4))
    head, img = encode_frame(frame)
    item = decode_message([head, auth_tag(SECRET, head), img.tobytes()], secret=SECRET)
    assert isinstance(item, Frame) and item.header == frame.header


def test_a_busy_address_or_a_loose_pairing_folder_touch_no_mosaic(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Defect 2 (the transport's part): the receiver binds, and checks its pairing folder,
    before the mosaic is created or an old one replaced (``--overwrite``)."""
    cfg = tiny_config(path=str(tmp_path / "keep.zarr"))
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    keep = zarr.open_group(str(tmp_path / "keep.zarr"), mode="w")
    keep.update_attributes({"mine": 1})
    before = sorted(p.name for p in (tmp_path / "keep.zarr").iterdir())
    address = f"tcp://127.0.0.1:{free_port()}"
    first = receive_frames(address, tiny_config(), first_timeout_s=30)
    try:
        rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address,
                   "--overwrite"])
    finally:
        first.close()
    assert rc == 2 and "cannot listen" in capsys.readouterr().err
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    folder = pairing_path(address).parent
    folder.mkdir(mode=0o700)
    folder.chmod(0o777)
    rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address,
               "--overwrite"])
    assert rc == 2 and f"{folder}: " in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "keep.zarr").iterdir()) == before
    assert zarr.open_group(str(tmp_path / "keep.zarr"), mode="r").attrs["mine"] == 1


def test_a_scan_fed_ids_jumping_to_2_62_is_incomplete_and_records_no_gap(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Defect 6 end to end: it ended 'complete' with 'frames_lost 4611686018427387874'."""
    cfg = tiny_config(path=str(tmp_path / "m.zarr"))
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    address = f"tcp://127.0.0.1:{free_port()}"
    frames = _frames(12)
    n = cfg.optics.n_levels  # in step with the focus staircase: only the ids are wrong
    send = frames[:8] + [Frame(f.header.model_copy(update={
        "frame_id": 2**62 + i, "focus_index": (2**62 + i) % n}), f.image)
        for i, f in enumerate(frames[8:])]

    def run() -> None:
        with FrameSender(address) as sender:  # paired through the receiver's file
            for f in send:
                sender.send(f)
            sender.end()

    t = threading.Thread(target=run)
    t.start()
    try:
        rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address,
                   "--record", str(tmp_path / "rec.zarr")])
    finally:
        t.join(60)
    out = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE, out.err
    assert "frame_id 4611686018427387904 is past the receiver's plan of" in out.err
    assert "frames_lost 4611686018427387" not in out.out + out.err
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs.asdict()
    assert attrs["status"] == "incomplete" and attrs["frames_received"] == 8
    assert attrs["frames_expected"] == frame_count(cfg)
    from sffscan.pipeline.formats.recording_reader import open_recording

    r = open_recording(tmp_path / "rec.zarr")
    assert r.report.frames == 8 and r.report.gaps == [] and r.report.last_id == 7
