"""The layers of DEVELOPERS.md, checked by import-linter (``[tool.importlinter]`` in
pyproject.toml): ``stages`` computes and never imports ``pipeline``, which runs and stores.

import-linter reads the installed ``sffscan`` package (its module graph includes imports
inside functions), so it runs from outside the checkout, where ``sffscan`` is the editable
install rather than the source folder.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _lint_imports() -> str:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert exe, "lint-imports (import-linter, a test dependency) is not installed"
    return exe


def test_stages_never_import_pipeline(tmp_path: Path) -> None:
    run = subprocess.run([_lint_imports(), "--no-logo", "--no-cache",
                          str(ROOT / "pyproject.toml")],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "1 kept, 0 broken" in run.stdout


def test_the_contract_catches_an_upward_import(tmp_path: Path) -> None:
    """The same contract on a two-module package whose ``stages`` imports ``pipeline``
    fails, naming the import: the check can fail."""
    pkg = tmp_path / "src" / "sffscan"
    for sub in ("stages", "pipeline"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "pipeline" / "config.py").write_text("X = 1\n")
    (pkg / "stages" / "depth.py").write_text(
        "def f():\n    from sffscan.pipeline.config import X\n    return X\n")
    contract = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    start = contract.index("[tool.importlinter]")
    end = contract.index("\n[tool.", start + 1)
    (tmp_path / "pyproject.toml").write_text(contract[start:end], encoding="utf-8")
    run = subprocess.run([_lint_imports(), "--no-logo", "--no-cache",
                          str(tmp_path / "pyproject.toml")],
                         cwd=tmp_path / "src", capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(tmp_path / "src"), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 1, run.stdout + run.stderr
    assert "sffscan.stages.depth -> sffscan.pipeline.config" in run.stdout
