"""``sffscan batch`` on a running Dask cluster whose workers are daemonic processes (as
``dask worker``'s are), given relative paths (issue 26 item 14)."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from pathlib import Path

import dask
import pytest
import zarr
from distributed import Client, LocalCluster
from sffscan.pipeline.batch import run_batch
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.sim_source import simulate_frames

from tests.scan_helpers import small_config


def _daemonic() -> bool:
    return bool(multiprocessing.current_process().daemon)


@pytest.fixture(scope="module")
def cluster() -> Iterator[LocalCluster]:
    """One worker process on loopback, daemonic (Dask's default, as 'dask worker')."""
    with dask.config.set({"distributed.worker.daemon": True}), \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                         host="127.0.0.1", dashboard_address="127.0.0.1:0",
                         memory_limit=0) as c:
        yield c


@pytest.fixture(scope="module")
def layers(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("dask") / "layers"
    d.mkdir()
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 3.0},
                       processing={"registration": False})
    writer = RecordingWriter(d / "layer_000.zarr", cfg)
    for frame in simulate_frames(cfg):
        writer.write(frame)
    writer.close()
    return d


def test_a_task_on_a_daemonic_worker_runs_its_stages_as_threads(
        cluster: LocalCluster, layers: Path, tmp_path: Path) -> None:
    with Client(cluster) as client:  # the failure of the issue needs daemonic workers
        assert all(client.run(_daemonic).values())
    # processes asked for (what 'auto' gives a full-size recording): a daemonic worker
    # cannot start them ('daemonic processes are not allowed to have children' before)
    rows = run_batch([layers / "layer_000.zarr"], tmp_path / "out",
                     scheduler=cluster.scheduler_address, evaluate=False,
                     processing={"execution": "processes"})
    assert rows[0].status == "complete", rows[0].error
    assert zarr.open_group(rows[0].mosaic, mode="r").attrs["status"] == "complete"


def test_relative_paths_reach_the_workers_resolved(
        cluster: LocalCluster, layers: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the worker started in another folder than the one the paths are relative to
    monkeypatch.chdir(layers.parent)
    rows = run_batch([Path("layers/layer_000.zarr")], Path("rel-out"),
                     scheduler=cluster.scheduler_address, evaluate=False)
    assert rows[0].status == "complete", rows[0].error
    assert Path(rows[0].mosaic) == layers.parent / "rel-out" / "layer_000.mosaic.zarr"
    assert Path(rows[0].mosaic).is_dir()
