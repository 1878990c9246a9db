"""The built wheel: one top-level package ``sffscan`` (nothing named ``pipeline`` or
``stages`` lands in site-packages), its JSON Schemas and ``py.typed`` as package data.

Building the wheel takes about 20 s on the 2-core VM: the test is marked ``slow`` (it runs
in CI with the rest; ``-m "not slow"`` leaves it out locally).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: what the build needs from the checkout (copied, so that no build/ folder, stale or
#: shared with other builds, is written into or read from the checkout)
SOURCES = ("pyproject.toml", "README.md", "LICENSE", "sffscan", "pipeline", "stages", "schemas")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(path, src / name)
    out = tmp_path_factory.mktemp("dist")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps",
                          "--no-build-isolation", "--no-index", "-q", str(src), "-w", str(out)],
                         capture_output=True, text=True, timeout=600, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
    wheels = list(out.glob("sffscan-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


@pytest.mark.slow
def test_wheel_holds_one_package_with_its_data(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/", 1)[0] for n in names}
    dist_info = {t for t in top if t.endswith(".dist-info")}
    assert top - dist_info == {"sffscan"}, sorted(top)
    assert not any(n.startswith(("pipeline/", "stages/", "schemas/")) for n in names)
    for sub in ("pipeline/cli/main.py", "pipeline/formats/schema_gen.py", "stages/mosaic.py",
                "stages/sim/world.py", "stages/fields/image_io.py", "api.py", "py.typed"):
        assert f"sffscan/{sub}" in names, sub
    from sffscan.pipeline.formats.schema_gen import SCHEMAS

    for schema in SCHEMAS:
        assert f"sffscan/schemas/{schema}" in names, schema
    assert "sffscan/schemas/__init__.py" in names
    # every module of the source folders is in the wheel (a new sub-package missing from
    # pyproject's package list would install a package that cannot import)
    mapped = {"sffscan": "sffscan", "pipeline": "sffscan/pipeline", "stages": "sffscan/stages"}
    missing = [f"{mapped[top]}/{path.relative_to(ROOT / top).as_posix()}"
               for top in mapped for path in (ROOT / top).rglob("*.py")
               if "__pycache__" not in path.parts]
    missing = [m for m in missing if m not in names]
    assert not missing, missing
    entry = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "sffscan = sffscan.pipeline.cli.main:main" in zipfile.ZipFile(wheel).read(
        entry).decode()


@pytest.mark.slow
def test_installed_wheel_imports_and_checks_its_schemas(wheel: Path, tmp_path: Path) -> None:
    """Unpacked into a folder of its own (as pip installs it, without the dependencies,
    which the test environment has): ``import sffscan`` and ``sffscan schemas --check``
    from an unrelated folder use the packaged copy."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    run = tmp_path / "elsewhere"
    run.mkdir()
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    code = ("import numpy, sffscan, sffscan.pipeline.formats.schema_gen as g; "
            "assert sffscan.focus_measure(numpy.eye(16), operator='LAPM', window=3).shape "
            "== (16, 16); print(sffscan.__file__); print(g.packaged_schema_dir())")
    res = subprocess.run([sys.executable, "-I", "-c", f"import sys; sys.path.insert(0, "
                          f"{str(site)!r}); {code}"], cwd=run, env=env, capture_output=True,
                         text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    module, schemas = res.stdout.split()
    assert module.startswith(str(site)) and schemas == str(site / "sffscan" / "schemas")
    res = subprocess.run([sys.executable, "-I", "-c", "import sys; sys.path.insert(0, "
                          f"{str(site)!r}); from sffscan.pipeline.cli.main import main; "
                          "raise SystemExit(main(['schemas', '--check']))"],
                         cwd=run, env=env, capture_output=True, text=True, timeout=120,
                         check=False)
    text = res.stdout + res.stderr
    assert f"schemas in {site / 'sffscan' / 'schemas'} (the packaged copy)" in text, text
