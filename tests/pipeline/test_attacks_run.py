"""Issue 23, the run path's parts attacked directly: configuration overrides and resume
identity (property-based, hypothesis), the writer lock across processes, the clash checks."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sffscan.pipeline import locks
from sffscan.pipeline.cli.common import override
from sffscan.pipeline.config import ConfigError, config_from_dict
from sffscan.pipeline.mosaic.writer import config_differences
from sffscan.pipeline.run import (
    RUN_ONLY,
    _with_run_only,
    check_clashes,
    check_file_output,
    identity_mismatch,
)

from tests.scan_helpers import small_config

#: fields a resume must refuse to change (they change what the mosaic measures)
MEASURING = {
    ("processing", "window"): st.sampled_from([3, 5, 7, 11]),
    ("processing", "depth_method"): st.sampled_from(["argmax", "gauss3", "spc", "adaptive"]),
    ("processing", "focus_operator"): st.sampled_from(["glvm", "lapm", "tenv"]),
    ("processing", "block_columns"): st.integers(1, 512),
    ("motion", "speed_mm_s"): st.sampled_from([5.0, 10.0, 15.0]),
}
RUN = {
    ("processing", "execution"): st.sampled_from(["auto", "threads", "processes"]),
    ("processing", "queue_capacity"): st.integers(1, 64),
    ("source", "idle_timeout_s"): st.sampled_from([1.0, 5.0, 30.0]),
    ("source", "max_bad_messages"): st.integers(1, 1000),
}


@settings(max_examples=60, deadline=None)
@given(recorded=st.booleans(), flag=st.booleans())
def test_a_replay_overwrites_only_with_its_own_flag(recorded: bool, flag: bool) -> None:
    cfg = small_config(output={"overwrite": recorded})
    args = argparse.Namespace(output="m.zarr", overwrite=flag)
    assert override(cfg, args, own_overwrite=False).output.overwrite is flag
    # a scan's own configuration file keeps its overwrite
    assert override(cfg, args).output.overwrite is (recorded or flag)


@settings(max_examples=80, deadline=None)
@given(run=st.fixed_dictionaries({k: st.one_of(st.none(), v) for k, v in RUN.items()}),
       measuring=st.fixed_dictionaries({k: st.one_of(st.none(), v)
                                        for k, v in MEASURING.items()}))
def test_resume_compares_what_a_mosaic_measures_not_how_it_ran(
        run: dict[tuple[str, str], object], measuring: dict[tuple[str, str], object]) -> None:
    old = small_config().model_dump(mode="json")
    data = small_config().model_dump()
    for (table, name), value in {**run, **measuring}.items():
        if value is not None:
            data[table][name] = value
    try:
        new = config_from_dict(data, origin="test").model_dump(mode="json")
    except ConfigError:
        return  # an infeasible combination: refused before any resume
    diff = config_differences(old, _with_run_only(new, old))
    changed = {f"{t}.{n}" for (t, n), v in measuring.items()
               if v is not None and old[t][n] != new[t][n]}
    assert set(diff) == changed
    assert not any(f"{t}.{n}" in diff for t, n in RUN_ONLY)


@settings(max_examples=80, deadline=None)
@given(path_a=st.sampled_from(["/r/a.zarr", "/r/b.zarr"]),
       path_b=st.sampled_from(["/r/a.zarr", "/r/b.zarr"]),
       id_a=st.sampled_from([None, "1", "2"]), id_b=st.sampled_from([None, "1", "2"]),
       dig_a=st.sampled_from(["x", "y"]), dig_b=st.sampled_from(["x", "y"]),
       frames_a=st.sampled_from([40, 80]), frames_b=st.sampled_from([40, 80]))
def test_identity_by_id_else_by_digest(path_a: str, path_b: str, id_a: str | None,
                                       id_b: str | None, dig_a: str, dig_b: str,
                                       frames_a: int, frames_b: int) -> None:
    stored = {"path": path_a, "id": id_a, "digest": dig_a, "frames": frames_a,
              "status": "complete"}
    current = {"path": path_b, "id": id_b, "digest": dig_b, "frames": frames_b,
               "status": "complete"}
    same = id_a == id_b if id_a and id_b else dig_a == dig_b
    assert (identity_mismatch(stored, current) is None) is same
    assert (identity_mismatch(stored, current, unchanged=True) is None) is (
        same and frames_a == frames_b)
    assert identity_mismatch(None, current) is None  # a mosaic that does not say


def test_clashes_between_outputs_and_inputs(tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    rec.mkdir()
    (rec / "zarr.json").write_text("{}")
    for out, inputs in ((rec, [rec]), (rec / "m.zarr", [rec]), (tmp_path, [rec])):
        cfg = small_config(output={"path": str(out)})
        with pytest.raises(ConfigError, match="would destroy it"):
            check_clashes(cfg, inputs=inputs)
    cfg = small_config(output={"path": str(tmp_path / "m.zarr")})
    check_clashes(cfg, inputs=[rec])  # side by side: fine
    with pytest.raises(ConfigError, match="overlaps output.path"):
        check_clashes(cfg, record=tmp_path / "m.zarr" / "rec.zarr")
    with pytest.raises(ConfigError, match="inside the Zarr store"):
        check_clashes(cfg, rrd=rec / "zarr.json")
    with pytest.raises(ConfigError, match="inside the Zarr store"):  # not created yet
        check_clashes(cfg, rrd=tmp_path / "m.zarr" / "view.rrd")
    with pytest.raises(ConfigError, match="is a folder"):
        check_file_output(tmp_path, "--x3p")
    check_clashes(cfg, rrd=tmp_path / "view.rrd")


HOLDER = """
import sys
from sffscan.pipeline import locks
held = locks.acquire(sys.argv[1])
print("held", flush=True)
sys.stdin.readline()
held.release()
"""


def test_the_lock_holds_across_processes_and_names_the_holder(tmp_path: Path) -> None:
    target = tmp_path / "m.zarr"
    with subprocess.Popen([sys.executable, "-c", HOLDER, str(target)], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True) as proc:
        try:
            assert proc.stdout is not None and proc.stdout.readline() == "held\n"
            with pytest.raises(locks.LockHeld, match=f"pid {proc.pid}") as err:
                locks.acquire(target)
            assert err.value.holder["pid"] == proc.pid
            assert locks.holder(target) == err.value.holder
        finally:
            assert proc.stdin is not None
            proc.stdin.write("\n")
            proc.stdin.flush()
            assert proc.wait(30) == 0
    assert locks.holder(target) is None and not locks.lock_path(target).exists()
    with locks.acquire(target):  # free again
        pass
    # a holder killed outright (kill -9) leaves its file; the kernel freed the lock
    with subprocess.Popen([sys.executable, "-c", HOLDER, str(target)], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None and proc.stdout.readline() == "held\n"
        proc.kill()
        proc.wait(30)
    assert locks.lock_path(target).exists() and locks.holder(target) is None
    with locks.acquire(target) as mine:
        assert mine.fd is not None


class _Holder:
    """Another process holding the writer lock of ``target`` (HOLDER) while in ``with``."""

    def __init__(self, target: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(target)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def __enter__(self) -> subprocess.Popen[str]:
        assert self.proc.stdout is not None and self.proc.stdout.readline() == "held\n"
        return self.proc

    def __exit__(self, *exc: object) -> None:
        assert self.proc.stdin is not None
        self.proc.communicate("\n", timeout=30)  # released; closes its pipes
        assert self.proc.returncode == 0


def test_stack_and_stop_and_go_refuse_a_mosaic_another_writer_holds(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A second writer of one mosaic (a scan, a stack or a stop-and-go run into the same
    output) is refused naming the holder before it reads or acquires anything; an existing
    output without --overwrite is refused before the stack is read too."""
    import cv2
    import numpy as np
    import zarr
    from sffscan.pipeline.cli import stack as stack_cli
    from sffscan.pipeline.cli.main import main
    from sffscan.pipeline.stopgo import SimFieldCamera, plan_grid, run_stop_and_go
    from sffscan.stages.sim.camera import Optics, focus_heights
    from sffscan.stages.sim.world import sinusoid_world

    rng = np.random.default_rng(0)
    files = []
    for k in range(5):
        files.append(str(tmp_path / f"z{k}.png"))
        assert cv2.imwrite(files[-1], rng.integers(0, 256, (24, 32), dtype=np.uint8))
    stack = ["stack", *files, "--focus-start", "0", "--focus-step", "10", "--pixel-um", "5"]
    out = tmp_path / "m.zarr"
    read = stack_cli.read_images
    reads: list[int] = []

    def counted(paths: list[str], *, grey: bool, progress: bool = True) -> np.ndarray:
        reads.append(len(paths))
        return read(paths, grey=grey, progress=progress)

    monkeypatch.setattr(stack_cli, "read_images", counted)  # where cmd_stack reads it
    with _Holder(out) as holder:
        assert main([*stack, "-o", str(out)]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
        assert not out.exists() and reads == []

        world = sinusoid_world(pixel_um=20.0, amplitude_um=3000.0, period_px=300.0,
                               offset_um=4800.0)
        acquired: list[float] = []

        class Counted(SimFieldCamera):
            def acquire(self, *, stage_x_um: float, stage_y_um: float) -> np.ndarray:
                acquired.append(stage_x_um)
                return super().acquire(stage_x_um=stage_x_um, stage_y_um=stage_y_um)

        cam = Counted(world, Optics(width=160, height=128, pixel_um=20.0),
                      focus_heights(n_levels=25, z_step_um=400.0))
        grid = plan_grid(x_um=(0.0, 4500.0), y_um=(0.0, 2000.0), field_px=(160, 128),
                         pixel_um=20.0, overlap_px=32)
        with pytest.raises(locks.LockHeld, match=f"pid {holder.pid}"):
            run_stop_and_go(cam, grid, out, overlap_px=32)
        assert not out.exists() and acquired == []
    assert main([*stack, "-o", str(out)]) == 0 and reads == [5]  # free again
    assert zarr.open_group(str(out), mode="r").attrs["status"] == "complete"
    assert not locks.lock_path(out).exists()
    capsys.readouterr()
    assert main([*stack, "-o", str(out)]) == 2  # exists: refused before the stack is read
    assert "exists; --overwrite" in capsys.readouterr().err and reads == [5]
    assert not locks.lock_path(out).exists()
    assert main([*stack, "-o", str(tmp_path / "new" / "deep" / "m.zarr")]) == 0  # folders made


def test_an_interruption_before_the_pipeline_runs_marks_the_mosaic_failed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import zarr
    from sffscan.pipeline import wiring
    from sffscan.pipeline.run import Job, execute

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C (or SIGTERM) before the stages start

    monkeypatch.setattr(wiring, "run_scan", interrupted)
    out = tmp_path / "m.zarr"
    with pytest.raises(KeyboardInterrupt):
        execute(Job(small_config(output={"path": str(out)}), frames=[]))
    assert zarr.open_group(str(out), mode="r").attrs["status"] == "failed"
    assert not locks.lock_path(out).exists()
