"""Authenticated transport (issue 13): only the paired sender delivers frames or ends a scan;
a third local process's forged end, forged frame, wrong key and 300 MB message are refused
and counted, and the scan completes with every frame; a killed sender leaves the scan
'incomplete' (exit 3) with the right counts."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.common import EXIT_INCOMPLETE
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.completeness import FrameAccount
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.formats.transport import FrameSender, TransportError, stream_frames
from sffscan.pipeline.formats.transport_auth import make_keys, pairing_path
from sffscan.pipeline.formats.transport_receiver import ReceiverStats, receive_frames
from sffscan.pipeline.plan import frame_count
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame

from tests.pipeline.formats.test_transport import ROOT, finish, free_port, start_grab, tiny_config

ATTACKER = r"""
import json, os, sys, time, zlib
import numpy as np, zmq
address = sys.argv[1]
ctx = zmq.Context()
def push():
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.LINGER, 5000)
    s.connect(address)
    return s
img = np.zeros((64, 160), np.uint16)
head = {"kind": "frame", "dtype": "uint16", "shape": [64, 160], "crc32": zlib.crc32(img.data),
        "header": {"frame_id": 10**12, "timestamp_ns": 2**62, "focus_index": 0}}
s = push()
s.send_multipart([json.dumps({"kind": "end", "frames_sent": 0}).encode(), b""])  # forged end
s.send_multipart([json.dumps(head).encode(), b"", img.tobytes()])  # forged frame, no tag
s.send_multipart([json.dumps(head).encode(), os.urandom(32), img.tobytes()])  # wrong key
big = push()
big.send(b"\0" * 300_000_000)  # 300 MB
s.close(); big.close(); ctx.term()
"""

KILLED_SENDER = r"""
import os, signal, sys
from sffscan.pipeline.config import load_config
from sffscan.pipeline.formats.transport import FrameSender
from sffscan.pipeline.sim_source import simulate_frames
cfg = load_config(sys.argv[1])
n = int(sys.argv[3])
sender = FrameSender(sys.argv[2])
for i, frame in enumerate(simulate_frames(cfg)):
    if i == n:
        break
    sender.send(frame)
sender.close(linger_s=30)  # every frame sent has left; then the process dies, no end message
os.kill(os.getpid(), signal.SIGKILL)
"""


def _peak_rss_reset() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def test_third_process_cannot_forge_nor_flood_the_scan(tmp_path: Path) -> None:
    cfg = tiny_config()
    address = f"tcp://127.0.0.1:{free_port()}"
    st, account = ReceiverStats(), FrameAccount(planned=frame_count(cfg), needs_sender=True)
    gen = receive_frames(address, cfg, first_timeout_s=60, stats=st, account=account)
    got: list[Frame] = []
    resettable = _peak_rss_reset()
    rss0 = _peak_rss_mb()
    receiver = threading.Thread(target=lambda: got.extend(gen))
    receiver.start()
    deadline = time.monotonic() + 30
    while not pairing_path(address).exists() and time.monotonic() < deadline:
        time.sleep(0.05)  # the receiver is listening once its pairing file exists
    assert pairing_path(address).stat().st_mode & 0o077 == 0  # only this user reads it
    attacker = subprocess.run([sys.executable, "-c", ATTACKER, address], cwd=ROOT,
                              capture_output=True, text=True, timeout=120, check=False)
    assert attacker.returncode == 0, attacker.stderr
    grab = start_grab(cfg, tmp_path, address)  # the paired sender, after the attack
    try:
        receiver.join(120)
        growth = _peak_rss_mb() - rss0
    finally:
        rc, err = finish(grab)
    assert not receiver.is_alive()
    assert rc == 0, err
    assert [f.header.frame_id for f in got] == list(range(frame_count(cfg)))
    assert st.ended and account.sent == frame_count(cfg)
    print(f"refused {st.rejected} messages, dropped {st.dropped_connections} connection(s), "
          f"peak RSS growth {growth:.1f} MB")
    assert st.rejected == 3  # forged end, forged frame, wrong key
    assert st.dropped_connections >= 1  # the 300 MB message's (and the attacker leaving)
    if resettable:
        assert growth < 50
    assert not pairing_path(address).exists()  # removed with the receiver


def test_bad_messages_are_fatal_only_past_the_limit() -> None:
    """The paired sender's unusable messages (here repeated frame ids) fail the scan past
    ``max_bad``; unauthenticated ones before them are dropped and never count."""
    cfg = tiny_config()
    address = f"tcp://127.0.0.1:{free_port()}"
    st = ReceiverStats()
    gen = receive_frames(address, cfg, first_timeout_s=30, max_bad=1, secret=b"s" * 32,
                         stats=st)
    forger = FrameSender(address, secret=b"w" * 32)
    paired = FrameSender(address, secret=b"s" * 32)
    frame = next(simulate_frames(cfg))
    try:
        for _ in range(3):
            forger.send(frame)
        forger.end(timeout_s=5)
        paired.send(frame)
        paired.send(Frame(frame.header, frame.image.copy()))
        paired.send(Frame(frame.header, frame.image.copy()))
        assert next(gen).header.frame_id == frame.header.frame_id
        with pytest.raises(TransportError, match="2 messages of the paired sender refused.*"
                                                 "max_bad_messages = 1.*repeated"):
            next(gen)
        # zmq queues each peer fairly: some of the forger's may still wait, none counted
        assert st.rejected - st.unauthenticated == 2
    finally:
        forger.close(linger_s=0)
        paired.close(linger_s=0)
        gen.close()


def test_curve_beyond_loopback_refuses_a_wrong_key(tmp_path: Path) -> None:
    """CURVE (forced on loopback here): the authorised sender's frames arrive, a sender with
    keys the receiver never authorised is cut off at the handshake and counted."""
    keys, other = tmp_path / "keys", tmp_path / "other"
    make_keys(keys)
    make_keys(other)
    assert main(["keys", "--dir", str(keys)]) == 2  # never replaced silently
    cfg = tiny_config()
    address = f"tcp://127.0.0.1:{free_port()}"
    st, account = ReceiverStats(), FrameAccount(needs_sender=True)
    gen = receive_frames(address, cfg, first_timeout_s=30, stats=st, account=account,
                         keys_dir=keys, curve=True)
    frames = [f for _, f in zip(range(3), simulate_frames(cfg), strict=False)]

    def send(folder: Path) -> None:
        sender = FrameSender(address, keys_dir=folder, curve=True)
        try:
            stream_frames(iter(frames), sender)
        except TransportError:
            pass  # the unauthorised sender's end times out
        finally:
            sender.close(linger_s=1)

    intruder = threading.Thread(target=send, args=(other,))
    intruder.start()
    time.sleep(0.5)  # let the intruder's handshake fail first (the test still holds if not)
    good = threading.Thread(target=send, args=(keys,))
    good.start()
    got = list(gen)
    good.join(30)
    intruder.join(30)
    assert [f.header.frame_id for f in got] == [0, 1, 2]
    assert st.ended and account.expected == 3
    assert st.dropped_connections >= 1
    for a, b in zip(got, frames, strict=True):
        np.testing.assert_array_equal(a.image, b.image)


def test_a_killed_sender_leaves_the_scan_incomplete_with_counts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tiny_config(path=str(tmp_path / "m.zarr"))
    data = cfg.model_dump()
    data["source"]["idle_timeout_s"] = 1.5
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(type(cfg).model_validate(data)), encoding="utf-8")
    total = frame_count(cfg)
    third = total // 3
    address = f"tcp://127.0.0.1:{free_port()}"
    sender = subprocess.Popen([sys.executable, "-c", KILLED_SENDER, str(toml), address,
                               str(third)], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        rc = main(["scan", "--config", str(toml), "-q", "--no-evaluate", "--source", address,
                   "--record", str(tmp_path / "rec.zarr")])
    finally:
        sender_err = sender.communicate(timeout=60)[1]
    assert sender.returncode == -9, sender_err  # killed, no end message
    out = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE == 3, out.err
    attrs = zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs.asdict()
    assert attrs["status"] == "incomplete"
    assert attrs["frames_expected"] == total and attrs["frames_received"] == third
    assert f"{third} frames received" in out.out
    assert "INCOMPLETE" in out.err
    assert main(["info", str(tmp_path / "m.zarr")]) == 0
    info = capsys.readouterr().out
    assert f"{third} of {total}" in info
    # the replay of its recording is incomplete too, with the same counts
    assert main(["replay", str(tmp_path / "rec.zarr"), "-o", str(tmp_path / "r.zarr"), "-q"]
                ) == EXIT_INCOMPLETE
    rattrs = zarr.open_group(str(tmp_path / "r.zarr"), mode="r").attrs.asdict()
    assert (rattrs["status"], rattrs["frames_received"]) == ("incomplete", third)
    assert json.dumps(rattrs["frames_expected"]) == json.dumps(total)


def test_a_receiver_beyond_loopback_without_keys_is_refused_before_anything(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tiny_config(path=str(tmp_path / "m.zarr"))
    data = cfg.model_dump()
    data["source"]["keys_dir"] = str(tmp_path / "nokeys")
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(type(cfg).model_validate(data)), encoding="utf-8")
    assert main(["scan", "--config", str(toml), "-q", "--source", "tcp://0.0.0.0:5599"]) == 2
    assert "sffscan keys" in capsys.readouterr().err
    assert not (tmp_path / "m.zarr").exists()
