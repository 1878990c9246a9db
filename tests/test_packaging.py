"""The built wheel: one top-level package ``sffscan`` (nothing named ``pipeline`` or
``stages`` lands in site-packages), its JSON Schemas and ``py.typed`` as package data.

Building the wheel takes about 20 s on the 2-core VM: the test is marked ``slow`` (it runs
in CI with the rest; ``-m "not slow"`` leaves it out locally).
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import tomllib
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


# --- what is declared ----------------------------------------------------------------------

#: import name -> distribution name, for imports whose distribution is not installed here
#: (where it is, importlib.metadata says)
DISTRIBUTION_OF = {"cv2": "opencv-python-headless", "pywt": "PyWavelets", "zmq": "pyzmq",
                   "rerun": "rerun-sdk", "PIL": "pillow", "google_crc32c": "google-crc32c"}


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _declared() -> dict[str, set[str]]:
    """pyproject's dependencies: canonical distribution name -> where ("dependencies" or
    the extra's name)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    groups = {"dependencies": project["dependencies"], **project["optional-dependencies"]}
    out: dict[str, set[str]] = {}
    for group, reqs in groups.items():
        for req in reqs:
            match = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", req)
            assert match, req
            out.setdefault(_canonical(match.group()), set()).add(group)
    return out


def _third_party_imports() -> dict[str, set[str]]:
    """Top-level third-party modules the package imports (anywhere in a module, deferred
    imports too) -> the files that import them."""
    found: dict[str, set[str]] = {}
    for top in ("sffscan", "pipeline", "stages", "schemas"):
        for path in (ROOT / top).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    first = name.split(".")[0]
                    if first not in sys.stdlib_module_names and first not in (
                            "sffscan", "__future__"):
                        found.setdefault(first, set()).add(str(path.relative_to(ROOT)))
    return found


def test_every_third_party_import_is_declared() -> None:
    """A module the product imports comes from a distribution that pyproject declares (as
    a dependency or in a feature's extra; ``[test]`` alone does not count): google_crc32c
    and numcodecs were imported by the chunk path but came only through zarr."""
    from importlib.metadata import packages_distributions

    installed = packages_distributions()
    declared = _declared()
    imports = _third_party_imports()
    assert {"numpy", "zarr", "google_crc32c", "numcodecs", "torch"} <= set(imports)
    missing = {}
    for module, files in sorted(imports.items()):
        dists = installed.get(module) or [DISTRIBUTION_OF.get(module, module)]
        if not any(declared.get(_canonical(d), set()) - {"test"} for d in dists):
            missing[module] = (dists, sorted(files))
    assert not missing, f"imported but not declared in pyproject (module: distributions, " \
                        f"files): {missing}"


def test_torch_is_an_extra_and_its_absence_names_it() -> None:
    """The main install has no torch (the CPU scan does not import it); a torch operator
    asked for without torch says which extra to install."""
    declared = _declared()
    assert declared["torch"] == {"torch"}, declared["torch"]
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    assert any(r.startswith("sffscan[") and "torch" in r for r in extras["test"])
    code = ("import sys; sys.modules['torch'] = None\n"  # as if torch were not installed
            "import numpy as np, sffscan\n"
            "img = np.eye(16, dtype=np.float32)\n"
            "assert sffscan.focus_measure(img, operator='glvm', window=3).shape == (16, 16)\n"
            "try:\n"
            "    sffscan.focus_measure(img, operator='lapm', window=3)\n"
            "except ModuleNotFoundError as err:\n"
            "    print(err.name, '|', err)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=False, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    name, message = res.stdout.split("|", 1)
    assert name.strip() == "torch" and "pip install 'sffscan[torch]'" in message, res.stdout


# --- where sffscan is found --------------------------------------------------------------

#: the README's install (a static path, so that a folder named sffscan beside a script does
#: not shadow the package, and mypy and IDEs find it)
INSTALL_HINT = "pip install -e . --config-settings editable_mode=strict (see the README)"


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True,
                          text=True, timeout=120, check=False)


def test_a_folder_named_sffscan_beside_a_script_does_not_shadow_the_package(
        tmp_path: Path) -> None:
    """A script or notebook in the folder that holds the clone (a folder ``sffscan`` without
    ``__init__.py``) imports the installed package, not the folder as an empty namespace
    package (``module 'sffscan' has no attribute 'demo_config'``)."""
    (tmp_path / "sffscan" / "pipeline").mkdir(parents=True)  # as a clone named sffscan
    res = _python("import sffscan; print(sffscan.demo_config().optics.width_px)", tmp_path)
    assert res.returncode == 0 and res.stdout.split() == ["1280"], \
        f"{res.stderr[-600:]}\ninstalled as the README says? {INSTALL_HINT}"


def test_the_source_tree_imports_whole_from_the_clone_s_folder() -> None:
    """From the clone's own folder (on sys.path first: ``python -m pytest``, a script in the
    clone) ``sffscan`` is the source folder, and its sub-packages are the clone's top-level
    folders: the package-dir mapping holds without the install's import hook."""
    res = _python("import sffscan, sffscan.pipeline.config as c, sffscan.stages.depth as d, "
                  "sffscan.schemas as s; print(sffscan.__file__, c.__file__, d.__file__)", ROOT)
    assert res.returncode == 0, res.stderr[-600:]
    init, config, depth = (Path(p) for p in res.stdout.split())
    assert init == ROOT / "sffscan" / "__init__.py"
    assert (config, depth) == (ROOT / "pipeline" / "config.py", ROOT / "stages" / "depth.py")


def test_mypy_finds_sffscan_for_a_user_script(tmp_path: Path) -> None:
    """mypy on a user's script outside the clone finds the installed sffscan (an import hook,
    which the default editable install uses, is invisible to mypy and IDEs)."""
    script = tmp_path / "user_script.py"
    script.write_text("import sffscan\n\ncfg: sffscan.ScanConfig = sffscan.demo_config()\n")
    res = subprocess.run([sys.executable, "-m", "mypy", "--follow-imports=skip",
                          "--cache-dir", str(tmp_path / ".mypy_cache"), "--no-incremental",
                          str(script)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300, check=False)
    assert res.returncode == 0, f"{res.stdout[-600:]}\ninstalled as the README says? " \
                                f"{INSTALL_HINT}"
