"""Shared test options and fixtures.

``--device`` picks the torch device the torch operators are tested on (default ``cpu``);
run ``pytest --device cuda`` on a machine with a GPU to test the CUDA path too.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

#: where tests/scan_helpers.py keeps the session's rendered scans (set by ``frame_cache``)
FRAME_CACHE_ENV = "SFFSCAN_TEST_FRAME_CACHE"

PERTUZ_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "pertuz-simu02"


#: the files whose tests take longest, longest first (each file's summed test time, two
#: whole runs on the 2-core AMD VM, 2026-12-03: test_optics_bars_fields 36-39 s,
#: test_scan_pipeline 31-33 s, test_parallel_scan 27-35 s, test_focus_operators ~25 s, then
#: 20 s down to ~9 s): collected first, so that with pytest-xdist's ``--dist loadfile`` no
#: worker is left alone with one of them at the end of the run. xdist (3.5 on) reorders
#: files by their number of tests unless told not to (``--no-loadscope-reorder``, xdist
#: 3.8, in pyproject.toml): that put the heavy files of few tests last, and one worker ran
#: test_optics_bars_fields alone for the last ~27 s of a 264 s run.
SLOW_FIRST = ("test_optics_bars_fields.py", "test_scan_pipeline.py", "test_parallel_scan.py",
              "test_focus_operators.py", "test_optics_bars.py", "test_scan_errors.py",
              "test_crash.py", "test_parallel.py", "test_moonraker_trapq.py",
              "test_scan_bars.py", "test_run_path.py", "test_batch.py",
              "test_mosaic_pyramid.py", "test_octoprint_link.py", "test_batch_resume.py",
              "test_printjob_service_store.py", "test_packaging.py", "test_viz.py",
              "test_replay.py", "test_transport_auth.py")


#: thread pools of the test processes' libraries, one thread each unless the caller's
#: environment says otherwise: the xdist workers (one more than the cores) and the
#: processes the tests start already share the cores, and OpenBLAS's and OpenMP's pools of
#: a thread per core on top of them oversubscribe it. Whole suite on the 2-core AMD VM
#: (2026-12-05, runs alternated): 294.5 / 307.2 s and 465 / 487 s of user CPU with the
#: libraries' defaults, 278.7 / 297.7 s and 443 / 448 s with one thread. The sffscan
#: processes the tests start set their own (the workers' BLAS limit, OpenCV's threads).
ONE_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def pytest_configure(config: pytest.Config) -> None:
    """Under CI (``CI`` set, as ``.ci/run``'s callers do) Hypothesis draws the same examples
    every run (``derandomize``, no example database): a gating run must not fail on one draw
    and pass on the next. Runs elsewhere keep drawing fresh examples, which is how a
    property's counter-example is found (the wire header test's transposed shape, found
    2026-12-05, is kept as an ``@example``). :data:`ONE_THREAD_ENV` is set here, before
    pytest-xdist starts its workers (they and the processes tests start inherit it)."""
    for name in ONE_THREAD_ENV:
        os.environ.setdefault(name, "1")
    from hypothesis import settings

    settings.register_profile("ci", derandomize=True, database=None)
    if os.environ.get("CI"):
        settings.load_profile("ci")


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one xdist worker more than the cores this process may run on (pyproject's
    ``--maxprocesses`` caps it). Many tests wait on processes they start (workers, servers,
    the command line), so two workers used 165-175 % of a 2-core machine's 200 %: five whole
    runs one after the other on the 2-core AMD VM (2026-12-05), two workers 319.6 and 302.8 s
    (165 and 175 % CPU), three 296.0 and 293.8 s (185 and 186 %), four 295.1 s (188 %)."""
    from sffscan.pipeline.cores import cores_available

    return cores_available() + 1


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))  # stable


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", help="torch device for operator tests (cpu, cuda)")


@pytest.fixture(scope="session")
def device(request: pytest.FixtureRequest) -> str:
    dev = str(request.config.getoption("--device"))
    if dev.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            pytest.fail(f"--device {dev} asked for, but torch.cuda.is_available() is False")
    return dev


@pytest.fixture(scope="session")
def pertuz_dir() -> Path:
    if not (PERTUZ_DIR / "imdata.mat").is_file():
        pytest.fail(f"pertuz-simu02 dataset not found at {PERTUZ_DIR} "
                    "(expected ../shared beside the checkout)")
    return PERTUZ_DIR


@pytest.fixture(scope="session", autouse=True)
def frame_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The folder of the session's simulated scans, each rendered once (FRAME_CACHE_ENV,
    tests/scan_helpers.FrameCache), in this session's temporary folder: with pytest-xdist,
    the folder above the workers' own, which all the session's workers share."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if "PYTEST_XDIST_WORKER" in os.environ else base) / "frame-cache"
    old = os.environ.get(FRAME_CACHE_ENV)
    os.environ[FRAME_CACHE_ENV] = str(root)
    yield root
    if old is None:
        del os.environ[FRAME_CACHE_ENV]
    else:
        os.environ[FRAME_CACHE_ENV] = old


@pytest.fixture
def sigint_handled() -> Iterator[None]:
    """SIGINT handled, not ignored, in this process while the test runs, so that a child it
    starts gets Python's Ctrl-C handling: a process started with SIGINT ignored (a background
    job of a shell without job control) hands SIG_IGN on to its children, which then run to
    their end through a Ctrl-C (the test fails, after a whole scan)."""
    old = signal.getsignal(signal.SIGINT)
    if old == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)
