"""Files written past the page cache: the same bytes as a plain write, refusals sent back to
the caller, other failures raised with nothing left behind."""

from __future__ import annotations

import errno
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from sffscan.pipeline.formats.unbuffered import ALIGN, UnbufferedFiles

SIZES = [1, ALIGN - 1, ALIGN, ALIGN + 1, 3 * ALIGN + 5, (1 << 20) + 17, (3 << 20) - 3]


def _parts(n: int, seed: int) -> tuple[bytes, bytes]:
    data = os.urandom(n) if seed < 0 else bytes((i * 131 + seed) % 251 for i in range(n))
    return data[: n - min(n, 4)], data[n - min(n, 4):]  # a body and a tail, as a chunk's


def test_the_file_holds_exactly_the_bytes_given_whatever_its_length(tmp_path: Path) -> None:
    u = UnbufferedFiles(min_bytes=0)
    for i, n in enumerate(SIZES):
        body, tail = _parts(n, i)
        path = tmp_path / f"f{i}"
        if not u.write(path, (body, tail)):  # this file system has no O_DIRECT
            assert not path.exists() and u.refused == 1
            pytest.skip(f"{tmp_path}: the file system refuses O_DIRECT (fallback: below)")
        assert path.read_bytes() == body + tail, n
        assert path.stat().st_size == n
        plain = tmp_path / f"plain{i}"
        plain.write_bytes(body + tail)  # the permissions a plain write gives (the umask's)
        assert path.stat().st_mode == plain.stat().st_mode
    assert u.written == len(SIZES)
    u.close()
    assert u.write(tmp_path / "after-close", (b"x" * 5000,))
    assert (tmp_path / "after-close").read_bytes() == b"x" * 5000


def test_small_or_empty_files_are_left_to_the_caller(tmp_path: Path) -> None:
    u = UnbufferedFiles(min_bytes=1 << 18)
    assert not u.write(tmp_path / "small", (b"a" * ((1 << 18) - 1),))
    assert not UnbufferedFiles(min_bytes=0).write(tmp_path / "empty", (b"",))
    assert not (tmp_path / "small").exists() and not (tmp_path / "empty").exists()
    assert u.written == u.refused == 0
    with pytest.raises(ValueError, match="min_bytes"):
        UnbufferedFiles(min_bytes=-1)


def test_a_file_system_that_refuses_o_direct_at_open_is_asked_once(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[int] = []
    real_open = os.open

    def refusing(path: Any, flags: int, mode: int = 0o777) -> int:
        opened.append(flags)
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument", str(path))
        return real_open(path, flags, mode)

    monkeypatch.setattr(os, "open", refusing)
    monkeypatch.setattr(os, "O_DIRECT", getattr(os, "O_DIRECT", 0o40000), raising=False)
    u = UnbufferedFiles(min_bytes=0)
    assert not u.write(tmp_path / "a", (b"1" * 10_000,))
    assert not u.write(tmp_path / "b", (b"2" * 10_000,))
    assert len(opened) == 1 and u.refused == 2 and u.written == 0
    assert not any(tmp_path.iterdir())


def test_a_device_block_larger_than_the_alignment_is_a_refusal(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "O_DIRECT", getattr(os, "O_DIRECT", 0o40000), raising=False)
    real_open = os.open
    # the open succeeds without the flag where the file system has none (tmpfs)
    monkeypatch.setattr(os, "open", lambda p, f, m=0o777: real_open(p, f & ~os.O_DIRECT, m))

    def einval(fd: int, data: Any, offset: int) -> int:
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.setattr(os, "pwrite", einval)
    u = UnbufferedFiles(min_bytes=0)
    assert not u.write(tmp_path / "a", (b"1" * 10_000,))
    assert u.refused == 1 and not (tmp_path / "a").exists()


def test_other_failures_are_raised_and_leave_no_partial_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "O_DIRECT", getattr(os, "O_DIRECT", 0o40000), raising=False)
    real_open, real_pwrite = os.open, os.pwrite
    monkeypatch.setattr(os, "open", lambda p, f, m=0o777: real_open(p, f & ~os.O_DIRECT, m))
    calls: list[int] = []

    def full_after_one_block(fd: int, data: Any, offset: int) -> int:
        calls.append(offset)
        if offset == 0:
            return real_pwrite(fd, memoryview(data)[:ALIGN], 0)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "pwrite", full_after_one_block)
    u = UnbufferedFiles(min_bytes=0)
    with pytest.raises(OSError, match="No space left"):
        u.write(tmp_path / "a", (b"1" * (5 * ALIGN),))
    assert calls == [0, ALIGN] and not (tmp_path / "a").exists()

    monkeypatch.setattr(os, "pwrite", lambda fd, data, offset: 100)  # not a whole block
    with pytest.raises(OSError, match="short unbuffered write"):
        u.write(tmp_path / "b", (b"1" * (5 * ALIGN),))
    assert not (tmp_path / "b").exists() and u.written == 0 and u.refused == 0


def test_a_real_full_disk_stops_the_recording_with_its_frames_readable(tmp_path: Path) -> None:
    """A small ext4 file system (loop-mounted: root only), which takes O_DIRECT: frames
    written past the cache until it is full, then ENOSPC, no partial chunk left, the frames
    before it readable."""
    import shutil
    import subprocess

    import numpy as np
    from sffscan.pipeline.config import demo_config
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.formats.recording_writer import RecordingWriter
    from sffscan.stages.messages import Frame, FrameHeader

    image, mnt = tmp_path / "fs.img", tmp_path / "mnt"
    mnt.mkdir()
    with open(image, "wb") as fh:
        fh.truncate(12 << 20)
    made = subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], capture_output=True,
                          check=False) if shutil.which("mkfs.ext4") else None
    mounted = made is not None and made.returncode == 0 and subprocess.run(
        ["mount", "-o", "loop", str(image), str(mnt)], capture_output=True,
        check=False).returncode == 0
    if not mounted:
        pytest.skip("cannot make and loop-mount an ext4 file system here (needs root, "
                    "mkfs.ext4 and a loop device)")
    try:
        cfg = demo_config()
        w = RecordingWriter(mnt / "rec.zarr", cfg)
        rng = np.random.default_rng(0)
        shape = (cfg.optics.height_px, cfg.optics.width_px)
        written = 0
        with pytest.raises(OSError) as exc:
            for i in range(100):  # ~1.7 MB each: the 12 MB file system fills
                w.write(Frame(FrameHeader(frame_id=i, timestamp_ns=i, focus_index=i % 50),
                              rng.integers(0, 1024, shape, dtype=np.uint16)))
                written += 1
        assert exc.value.errno == errno.ENOSPC
        assert w.unbuffered is not None and w.unbuffered.written == written > 0
        w.close(status="failed", error="disk full")
        assert not [p for p in (mnt / "rec.zarr" / "frames").iterdir() if "partial" in p.name]
        r = open_recording(mnt / "rec.zarr")
        assert r.attrs.status == "failed" and r.report.frames == written
        assert r.report.defects == 0
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True, check=False)


def _sink_frames(n: int) -> list[Any]:
    import numpy as np
    from sffscan.stages.messages import Frame, FrameHeader

    rng = np.random.default_rng(3)
    return [Frame(FrameHeader(frame_id=i, timestamp_ns=i * 6_666_667, focus_index=i % 50),
                  rng.integers(0, 1024, (256, 640), dtype=np.uint16)) for i in range(n)]


@pytest.mark.parametrize("slow", ["disk", "cpu"])
def test_a_recorder_behind_because_of_the_disk_goes_back_to_the_page_cache(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        slow: str) -> None:
    """Behind while waiting for the disk past the cache: the rest goes through the cache
    (said in a warning and the summary); behind for its own CPU: nothing changes."""
    import logging
    import time

    from sffscan.pipeline.formats import recorder_sink
    from sffscan.pipeline.formats import recording_writer as recorder
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.stages.protocol import Tapped

    from tests.scan_helpers import small_config

    if not UnbufferedFiles(min_bytes=0).write(tmp_path / "probe", (b"x",)):
        pytest.skip(f"{tmp_path}: the file system refuses O_DIRECT")
    real_pwrite, real_digest = os.pwrite, recorder.frame_digest

    def slow_disk(fd: int, data: Any, offset: int) -> int:
        time.sleep(0.004)
        return real_pwrite(fd, data, offset)

    def slow_cpu(*args: Any, **kwargs: Any) -> int:
        t = time.perf_counter()
        while time.perf_counter() - t < 0.008:  # twice the slow disk's wait: a margin
            pass
        return real_digest(*args, **kwargs)

    if slow == "disk":
        monkeypatch.setattr(os, "pwrite", slow_disk)
    else:
        monkeypatch.setattr(recorder, "frame_digest", slow_cpu)
        # the real disk's own wait stopped counting: on a loaded machine an O_DIRECT write
        # alone took 65 % of the busy time (a CI run), which is the other case's test
        from sffscan.pipeline.formats import unbuffered

        monkeypatch.setattr(unbuffered, "time", SimpleNamespace(perf_counter=lambda: 0.0))
    w = recorder.RecordingWriter(tmp_path / "rec.zarr", small_config())
    assert w.unbuffered is not None
    w.unbuffered.min_bytes = 4096  # the frames (256 x 640 px), not the header rows
    sink = recorder_sink.RecorderSink(w, fps=150.0, capacity=16, behind_share=0.5, window_s=0.05)
    frames = _sink_frames(40)
    with caplog.at_level(logging.WARNING, logger=recorder_sink.__name__):
        for f in frames:
            list(sink.process(Tapped("source", f)))
        list(sink.finish())
    stats = sink.extra_stats()
    assert sink.behind_windows > 0  # both ways it fell behind
    if slow == "disk":
        assert w.page_cache_from is not None and 0 < w.page_cache_from < len(frames)
        assert w.unbuffered.written == w.page_cache_from  # then the cache took the rest
        assert stats["page_cache_from_frame"] == w.page_cache_from
        assert f"from frame {w.page_cache_from} on it writes through the cache" in caplog.text
    else:
        assert w.page_cache_from is None and w.unbuffered.written == len(frames)
        assert "page_cache_from_frame" not in stats and "through the cache" not in caplog.text
    r = open_recording(tmp_path / "rec.zarr")
    assert r.attrs.status == "complete" and r.report.frames == len(frames)
    assert r.report.defects == 0
    for got, want in zip(r.frames(), frames, strict=True):
        assert got.header == want.header and (got.image == want.image).all()
