"""The progress display: a tqdm bar on a terminal, plain periodic lines elsewhere (never a
carriage return), the same figures either way; a failing stream switches it off."""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.progress import ProgressDisplay, ScanProgress
from sffscan.pipeline.stats import StageStats


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class _Closed(io.StringIO):
    def write(self, s: str) -> int:
        raise BrokenPipeError("closed")


def _stats(acquired: int, done: int) -> list[StageStats]:
    return [StageStats("source", frames=acquired), StageStats("depth", frames=done),
            StageStats("mosaic", frames=0)]


def test_plain_lines_every_few_seconds_without_carriage_returns() -> None:
    s = io.StringIO()
    p = ScanProgress(455, stream=s, every_s=5.0)
    assert not p.tty
    for t in range(0, 21):  # called every second for 20 s
        p(_stats(min(455, 25 * t + 5), min(455, 22 * t)), float(t))
    text = s.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 5  # at 0, 5, 10, 15, 20 s
    assert lines[0].startswith("frames 0/455 (0.0 %)")
    # frames done, rate, elapsed, time left, frames acquired
    assert lines[2] == ("frames 220/455 (48.4 %)  22.0 frames/s  elapsed 00:10  eta 00:10, "
                        "acquired 255")
    stats = _stats(455, 440)
    p(stats, 20.5)  # too soon for a line ...
    stats[1].frames = 455  # ... and the stages go on (their statistics are live objects)
    p.close()  # the final count, at once
    last = s.getvalue().splitlines()
    assert len(last) == 6 and last[-1].startswith("frames 455/455 (100.0 %)")


def test_bar_on_a_terminal_ends_its_line() -> None:
    s = _Terminal()
    p = ScanProgress(100, stream=s)
    assert p.tty
    for t in range(1, 5):
        p(_stats(25 * t, 25 * t), float(t))
    p.close()
    text = s.getvalue()
    assert "\r" in text and text.endswith("\n")
    assert re.search(r"100/100", text) and "acquired 100" in text


def test_bar_on_a_terminal_that_reports_no_size() -> None:
    """A pseudo-terminal of 0 x 0 (no size set, as under some CI runners and 'script'):
    tqdm alone draws nothing there; the display falls back to 100 x 20."""
    import os
    import pty

    master, slave = pty.openpty()
    try:
        assert os.get_terminal_size(slave) == os.terminal_size((0, 0))
        with open(slave, "w", closefd=False) as stream:
            p = ProgressDisplay(10, stream=stream)
            assert p.tty
            for i in range(11):
                p.update(i, 0.1 * i)
            p.close()
        # a pty hands its output over in pieces: read until nothing more comes
        import select

        chunks = []
        while select.select([master], [], [], 0.5)[0]:
            data = os.read(master, 65536)
            if not data:
                break
            chunks.append(data)
        text = b"".join(chunks).decode(errors="replace")
    finally:
        os.close(slave)
        os.close(master)
    assert "10/10" in text and "frames" in text


def test_a_closed_stream_switches_the_display_off() -> None:
    p = ProgressDisplay(10, stream=_Closed(), every_s=0.0)
    p.update(1, 1.0)  # must not raise
    p.update(2, 2.0)
    assert p.stream is None
    p.close()
    t = _Terminal()
    p = ProgressDisplay(10, stream=t)
    t.close()  # the terminal went away
    p.update(3, 1.0)
    p.close()


def test_stopgo_progress_in_a_log_file_has_no_carriage_return(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`stopgo` used to write '\\r' lines into a log file: now plain lines, one per few s."""
    out = tmp_path / "sg.zarr"
    assert main(["stopgo", "-o", str(out), "--area-mm", "3", "7", "0", "3", "--field", "160",
                 "128", "--levels", "25", "--z-step-um", "400"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert re.search(r"^fields 1/\d+ \(", err, flags=re.M), err


def test_below_one_item_per_second_the_line_says_seconds_per_item() -> None:
    """tqdm's ``rate`` field turns into seconds per item below one item per second: a field
    every 11.4 s was printed as "11.4 fields/s" (issue 26, item 2)."""
    s = io.StringIO()
    p = ProgressDisplay(5, desc="fields", stream=s, every_s=0.0)
    p.update(1, 11.4)
    p.update(30, 20.0)  # 1.5 fields/s: the items-per-second form again
    p.close()
    slow, fast = s.getvalue().splitlines()
    assert "11.4 s/field " in slow and "fields/s" not in slow
    assert "1.5 fields/s" in fast


def test_a_stage_after_the_depth_stage_counting_blocks_is_not_taken_for_frames() -> None:
    """With a calibration, a correction stage counting depth blocks stands between the
    depth stage and the mosaic: the display counted its blocks as frames (issue 26, item 2)."""
    s = io.StringIO()
    p = ScanProgress(455, stream=s, every_s=0.0)
    stats = [StageStats("source", frames=400), StageStats("depth", frames=390),
             StageStats("optics", unit="blocks", frames=52), StageStats("mosaic", frames=0)]
    p(stats, 10.0)
    p.close()
    assert s.getvalue().splitlines()[0].startswith("frames 390/455 (85.7 %)")
