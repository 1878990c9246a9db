"""Environments of the third-party programs the tests run against (OctoPrint, Moonraker,
the NGFF tools), each in a venv of its own because their pins clash with the project's.

Made with uv (a test dependency; its ``uv pip install`` resolves and installs from PyPI in
a few seconds: 2.6 s for the NGFF tools and 4.1 s for OctoPrint with an empty cache on the
2-core VM, against 36 s and 25 s with venv + pip), from the interpreter that runs the tests.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

__all__ = ["make_venv", "venv_install"]


def venv_install(venv: Path, *args: str, env: dict[str, str] | None = None,
                 timeout: float = 1800) -> subprocess.CompletedProcess[str]:
    """``uv pip install ARGS`` into ``venv`` (output captured, never raises)."""
    return subprocess.run([sys.executable, "-m", "uv", "pip", "install", "-q", "--python",
                           str(venv / "bin" / "python"), *args], capture_output=True,
                          text=True, timeout=timeout, env=env, check=False)


def make_venv(venv: Path, *args: str, env: dict[str, str] | None = None,
              timeout: float = 1800) -> subprocess.CompletedProcess[str]:
    """A new venv at ``venv`` (what was there is removed) with ``args`` installed."""
    shutil.rmtree(venv, ignore_errors=True)
    subprocess.run([sys.executable, "-m", "uv", "venv", "-q", "--python", sys.executable,
                    str(venv)], check=True, capture_output=True, timeout=300)
    return venv_install(venv, *args, env=env, timeout=timeout)
