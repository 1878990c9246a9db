"""Process execution: the scan pipeline in processes, the live viewer in process mode,
Ctrl-C and kill -9 of a process-mode scan (split from tests/pipeline/test_parallel.py so that
pytest-xdist's --dist loadfile can run the two halves on different workers).

The scan tests run the small test optics (tests/scan_helpers.py) with
``processing.execution = "processes"``: worker processes, frames in shared memory.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.common import run_and_report
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.formats.recorder_sink import recorder_sink
from sffscan.pipeline.runtime import StageFailed
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.viz.sink import VizOptions, VizSink, viz_sink_for
from sffscan.pipeline.wiring import format_summary, run_scan
from sffscan.pipeline.worker import WorkerGroup
from sffscan.stages.messages import DepthBlock
from sffscan.stages.protocol import Tapped

from tests.parallel_helpers import failing_focus_group, shm_names
from tests.scan_helpers import RenderedScan, small_config

ROOT = Path(__file__).resolve().parents[2]


# --- the scan pipeline in processes --------------------------------------------------------


@pytest.fixture(scope="module")
def scan_2_8() -> RenderedScan:
    """The 2-8 mm small scan, rendered once for the module's five scans of it (threads or
    processes: ``processing.execution`` does not change the frames, which the bit-identity
    test below checks)."""
    return RenderedScan(small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0}))


def mosaic_arrays(path: Path) -> dict[str, np.ndarray]:
    return {k: np.asarray(zarr.open_array(str(path / k), mode="r")[...])
            for k in ("height", "texture", "weight", "confidence")}


def test_process_mode_mosaic_is_bit_identical_to_thread_mode(tmp_path: Path) -> None:
    base = small_config(motion={"x_end_mm": 8.0, "wobble_along_px": 1.0})
    frames = list(simulate_frames(base))
    out = {}
    for mode in ("threads", "processes"):
        cfg = small_config(motion={"x_end_mm": 8.0, "wobble_along_px": 1.0},
                           processing={"execution": mode})
        rec = recorder_sink(cfg, str(tmp_path / f"{mode}.rec.zarr"))
        rep = run_scan(cfg, frames=iter(frames), output=tmp_path / f"{mode}.zarr",
                       progress=False, sinks=[rec])
        assert rep.frames == len(frames) and rep.result.dropped == 0
        assert ("processes" in rep.result.extras) == (mode == "processes")
        assert rep.result.extras["recorder"]["frames_recorded"] == len(frames)
        out[mode] = mosaic_arrays(tmp_path / f"{mode}.zarr")
        assert zarr.open_group(str(tmp_path / f"{mode}.zarr"), mode="r").attrs[
            "status"] == "complete"
    for k, a in out["threads"].items():
        assert a.shape == out["processes"][k].shape
        assert np.array_equal(a, out["processes"][k], equal_nan=True), k
    assert np.isfinite(out["processes"]["height"]).sum() > 1000
    # the recorder, in its own process, stored every frame bit for bit
    from sffscan.pipeline.formats.recording_reader import open_recording

    got = list(open_recording(tmp_path / "processes.rec.zarr").frames())
    assert [f.header for f in got] == [f.header for f in frames]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(got, frames, strict=True))


def test_calibrated_scan_in_processes_is_the_thread_placements_bit_for_bit(
        tmp_path: Path) -> None:
    """With a calibration that corrects the frames (magnification per level, vignetting:
    the frame_optics stage, whose frames are new arrays, not the source's slots) the
    process placement's mosaic is the thread placement's bit for bit."""
    from sffscan.pipeline.metrology.calibration_model import (
        Calibration,
        LateralScale,
        VignettingFit,
        ZResponse,
        save_calibration,
    )

    o = small_config().optics
    p, n = o.pixel_um, o.n_levels
    centre = ((o.width_px - 1) / 2, (o.height_px - 1) / 2)
    r2 = centre[0] ** 2 + centre[1] ** 2
    cal = save_calibration(Calibration(
        z_response=ZResponse(um_per_level=o.z_step_um, intercept_um=o.z_min_um, pearson_r=1.0,
                             heights_um=[o.z_min_um, o.z_min_um + (n - 1) * o.z_step_um],
                             peak_levels=[0.0, n - 1.0], residuals_um=[0.0, 0.0]),
        lateral=LateralScale(um_per_px_x=p, um_per_px_y=p, reference_level=(n - 1) / 2,
                             slope_x_per_level=-0.02 * p / (n - 1),
                             slope_y_per_level=-0.02 * p / (n - 1), optical_centre_px=centre),
        vignetting=VignettingFit(frame_width_px=o.width_px, frame_height_px=o.height_px,
                                 centre_px=centre,
                                 coefficients=(1.0, 0.0, 0.0, -0.2 / r2, 0.0, -0.2 / r2),
                                 corner_loss=0.2)), tmp_path / "cal.json")
    motion = {"x_end_mm": 6.0, "wobble_along_px": 1.0}
    frames = list(simulate_frames(small_config(motion=motion)))
    out = {}
    for mode in ("threads", "processes"):
        cfg = small_config(motion=motion, processing={"execution": mode,
                                                      "calibration": str(cal)})
        rep = run_scan(cfg, frames=iter(frames), output=tmp_path / f"{mode}.zarr",
                       progress=False)
        assert rep.frames == len(frames) and rep.result.dropped == 0
        assert ("processes" in rep.result.extras) == (mode == "processes")
        assert "frame_optics" in [s.name for s in rep.result.stages]
        out[mode] = mosaic_arrays(tmp_path / f"{mode}.zarr")
    for k, a in out["threads"].items():
        assert np.array_equal(a, out["processes"][k], equal_nan=True), k
    assert np.isfinite(out["processes"]["height"]).sum() > 1000


def test_a_failing_worker_stage_fails_the_scan_exit_1_mosaic_readable(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch, scan_2_8: RenderedScan) -> None:
    from sffscan.pipeline import scan_processes, wiring

    def with_failing_depth(cfg, stages, **kw):  # type: ignore[no-untyped-def]
        placement = scan_processes.process_placement(cfg, stages, **kw)
        placement.groups[-1] = WorkerGroup("focus", failing_focus_group,
                                           {"cfg": cfg.model_dump(mode="json"), "at": 90},
                                           ("focus_measure", "depth"))
        return placement

    monkeypatch.setattr(wiring, "process_placement", with_failing_depth)
    cfg = small_config(motion={"x_end_mm": 8.0}, processing={"execution": "processes"},
                       output={"path": str(tmp_path / "m.zarr")})
    assert cfg.model_copy(update={"processing": scan_2_8.cfg.processing,
                                  "output": scan_2_8.cfg.output}) == scan_2_8.cfg
    assert run_and_report(cfg, iter(scan_2_8), world=None, progress=False) == 1
    err = capsys.readouterr().err
    assert "stage 'depth' failed: FrameError: frame_id 90: injected failure" in err
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    assert g.attrs["status"] == "failed"
    assert np.isfinite(mosaic_arrays(tmp_path / "m.zarr")["height"]).sum() > 0  # kept
    assert not mp.active_children()


# --- the live viewer in process mode --------------------------------------------------------


def rrd_contents(path: Path) -> tuple[set[str], set[str], dict[str, list[float]]]:
    """Temporal and static entity paths of an .rrd, and the scalars of the viewer's drops
    in log order."""
    from rerun.chunk import RrdReader

    temporal: set[str] = set()
    static: set[str] = set()
    dropped: list[tuple[int, int, float]] = []
    for chunk in RrdReader(path).stream():
        (static if chunk.is_static else temporal).add(chunk.entity_path)
        if chunk.entity_path == "/stats/dropped/viewer" and not chunk.is_static:
            cols = chunk.to_record_batch().to_pydict()
            dropped += zip(cols["frame"], cols["rerun.controls.RowId"],
                           (v[0] for v in cols["Scalars:scalars"]), strict=True)
    return temporal, static, {"viewer": [v for *_, v in sorted(dropped)]}


def test_viewer_in_process_mode_logs_the_entities_of_thread_mode(
        tmp_path: Path, scan_2_8: RenderedScan) -> None:
    """``--viewer save --rrd`` in process mode: the same entity paths as in thread mode,
    the view's drops in the summary, nothing left behind."""
    got = {}
    for mode in ("threads", "processes"):
        cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0},
                           processing={"execution": mode})
        sink = viz_sink_for(cfg, ["save", str(tmp_path / f"{mode}.rrd")],
                            options=VizOptions(mosaic_max_px=320, mosaic_every_s=0.2))
        assert cfg.model_copy(update={"processing": scan_2_8.cfg.processing}) == scan_2_8.cfg
        rep = run_scan(cfg, frames=iter(scan_2_8), output=tmp_path / f"{mode}.zarr",
                       progress=False, sinks=[sink])
        assert ("processes" in rep.result.extras) == (mode == "processes")
        assert rep.result.dropped == 0
        assert all(s.frames == rep.frames for s in rep.result.stages[:5])
        q = [q for q in rep.result.queues if q.name.endswith("->viewer")]
        assert len(q) == 1 and q[0].policy == "drop_oldest"
        assert rep.result.extras["viewer"]["dropped_by_viewer"] == q[0].dropped
        assert f"{q[0].dropped:>7}" in format_summary(rep).split(q[0].name)[1].split("\n")[0]
        assert rep.result.extras["viewer"]["frames_logged"] > 0
        got[mode] = rrd_contents(tmp_path / f"{mode}.rrd")
        # the last statistics reach the view after every drop
        assert got[mode][2]["viewer"][-1] == q[0].dropped
    assert got["processes"][0] == got["threads"][0]
    assert got["processes"][1] == got["threads"][1]
    assert "/scan/focus/measure" in got["processes"][0]
    assert not mp.active_children()
    assert shm_names(os.getpid()) == []


class SlowViz(VizSink):
    """A viewer that cannot keep up (or, with ``fail``, fails at the end of its stream)."""

    def __init__(self, *args: Any, fail: bool = False, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.fail = fail
        self.blocks = 0

    def process(self, item: Any) -> tuple[()]:
        time.sleep(0.02)
        self.blocks += isinstance(item, Tapped) and isinstance(item.item, DepthBlock)
        return super().process(item)

    def finish(self) -> tuple[()]:
        if self.fail:
            raise RuntimeError("viewer broke")
        return super().finish()


def test_slow_viewer_in_process_mode_drops_and_never_holds_the_scan_back(
        tmp_path: Path, scan_2_8: RenderedScan) -> None:
    import rerun as rr

    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0},
                       processing={"execution": "processes"})
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "slow.rrd"))
    sink = SlowViz(cfg, rec, options=VizOptions(capacity=4))
    assert cfg.model_copy(update={"processing": scan_2_8.cfg.processing}) == scan_2_8.cfg
    rep = run_scan(cfg, frames=iter(scan_2_8), output=tmp_path / "m.zarr",
                   progress=False, sinks=[sink])
    q = [q for q in rep.result.queues if q.name.endswith("->viewer")][0]
    assert q.dropped > 0 and q.capacity == 4
    # what it dropped were frames: every depth block reached it (its mosaic has no hole)
    depth = next(s for s in rep.result.stages if s.name == "depth")
    assert depth.items_out > 3 and sink.blocks == depth.items_out
    assert rep.result.dropped == 0 and all(s.frames == rep.frames
                                           for s in rep.result.stages[:5])
    assert rep.result.extras["viewer"]["dropped_by_viewer"] == q.dropped
    assert rep.result.extras["viewer"]["pipeline_waited_s"] == 0.0
    assert zarr.open_group(str(rep.output), mode="r").attrs["status"] == "complete"
    assert rrd_contents(tmp_path / "slow.rrd")[2]["viewer"][-1] == q.dropped
    # a viewer that fails stops the scan with its name, like any stage; at the end of its
    # stream (after the mosaic's last block): the mosaic is still closed as failed, as in
    # thread mode, where the stages are closed after the sinks
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0},
                       processing={"execution": "processes"})
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "fail.rrd"))
    with pytest.raises(StageFailed, match="stage 'viewer' failed: RuntimeError: viewer broke"):
        run_scan(cfg, frames=iter(scan_2_8), output=tmp_path / "f.zarr",
                 progress=False, sinks=[SlowViz(cfg, rec, fail=True)])
    assert zarr.open_group(str(tmp_path / "f.zarr"), mode="r").attrs["status"] == "failed"
    assert not mp.active_children()
    assert shm_names(os.getpid()) == []


def long_scan_args(tmp_path: Path) -> list[str]:
    cfg = small_config(source={"plate_length_mm": 80.0}, motion={"x_end_mm": 78.0},
                       processing={"execution": "processes"})
    conf = tmp_path / "scan.toml"
    conf.write_text(config_to_toml(cfg), encoding="utf-8")
    return ["scan", "--config", str(conf), "--no-evaluate", "-q", "-o",
            str(tmp_path / "m.zarr"), "--viewer", "save", "--rrd", str(tmp_path / "v.rrd")]


def children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def start_scan(tmp_path: Path) -> tuple[subprocess.Popen[bytes], list[int]]:
    """A process-mode scan in a child; returns once its two workers are streaming."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "tests.parallel_helpers",
                             *long_scan_args(tmp_path)], cwd=ROOT, env=env,
                            stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        workers = [c for c in children(proc.pid)
                   if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
        if len(workers) >= 2 and not shm_names(proc.pid):  # attached: names unlinked
            # frames flow: a depth block has reached the mosaic (its first chunk written)
            if any((tmp_path / "m.zarr" / "height").glob("c/*/*")):
                assert proc.poll() is None, "the scan ended before it could be interrupted"
                return proc, workers
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        time.sleep(0.2)
    proc.kill()
    raise AssertionError("the workers did not start")


def test_ctrl_c_exits_130_with_everything_closed(
        tmp_path: Path, sigint_handled: None) -> None:
    proc, workers = start_scan(tmp_path)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()
    assert "interrupted" in err.decode()
    assert not any(alive(w) for w in workers)
    assert shm_names(proc.pid) == []
    assert zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs["status"] == "failed"


def test_kill_9_of_the_main_process_leaves_no_worker_and_no_shared_memory(
        tmp_path: Path) -> None:
    proc, workers = start_scan(tmp_path)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=10)
    t0 = time.monotonic()
    while any(alive(w) for w in workers) and time.monotonic() - t0 < 5.0:
        time.sleep(0.1)
    assert not any(alive(w) for w in workers), "a worker outlived the main process by 5 s"
    assert shm_names(proc.pid) == []


def test_measuring_workers_import_neither_zarr_nor_the_mosaic() -> None:
    """The worker factories of the process placement build their stages from
    sffscan.pipeline.measuring, which imports neither Zarr nor the mosaic writer (0.2-0.3 s
    of CPU at each worker's start; the main process writes the mosaic)."""
    code = ("import sys; import sffscan.pipeline.scan_processes as s; "
            "from sffscan.pipeline.config import ScanConfig; "
            "cfg = ScanConfig().model_dump(mode='json'); "
            "names = [x.name for x in s.registration_group(cfg) + s.focus_group(cfg)]; "
            "print(names, sorted(m for m in sys.modules "
            "if m == 'zarr' or m.startswith('sffscan.pipeline.mosaic')))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "['registration', 'focus_measure', 'depth'] []", run.stdout
