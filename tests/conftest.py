"""Shared test options and fixtures.

``--device`` picks the torch device the torch operators are tested on (default ``cpu``);
run ``pytest --device cuda`` on a machine with a GPU to test the CUDA path too.
"""

from __future__ import annotations

from pathlib import Path

import pytest

PERTUZ_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "pertuz-simu02"


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
