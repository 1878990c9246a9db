"""The documentation: the site builds with warnings as errors, the generated reference pages
match the model and the schemas, and the README stays short and keeps the CI command."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"


def _run(*args: str | Path, **kwargs) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # Material's banner, not a warning
    return subprocess.run([sys.executable, *map(str, args)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300, **kwargs)


@pytest.mark.parametrize("script,page", [("gen_config_reference.py", "configuration.md"),
                                         ("gen_formats_reference.py", "formats.md")])
def test_generated_page_is_current(script: str, page: str) -> None:
    """The committed page is what the script generates from the model (or schemas) now."""
    done = _run(DOCS / script, "--check")
    assert done.returncode == 0, done.stderr + done.stdout
    assert "up to date" in done.stdout


@pytest.mark.parametrize("script,page", [("gen_config_reference.py", "configuration.md"),
                                         ("gen_formats_reference.py", "formats.md")])
def test_drift_is_detected(tmp_path: Path, script: str, page: str) -> None:
    """A page whose field table no longer says what the model says fails the check."""
    text = (DOCS / page).read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| `"))
    cells = row.split(" | ")
    cells[2] = "`12345`"  # the default column
    stale = tmp_path / page
    stale.write_text(text.replace(row, " | ".join(cells), 1), encoding="utf-8")
    done = _run(DOCS / script, "--check", "--page", stale)
    assert done.returncode == 1
    assert f"{stale}: out of date" in done.stderr


def test_configuration_page_lists_every_field() -> None:
    """Every field of every section of the model has a row under its section's heading."""
    from sffscan.pipeline.config import ScanConfig

    text = (DOCS / "configuration.md").read_text(encoding="utf-8")
    for section, info in ScanConfig.model_fields.items():
        model = info.annotation
        if not isinstance(model, type) or not hasattr(model, "model_fields"):
            assert f"| `{section}` |" in text
            continue
        part = text.split(f"## `[{section}]`", 1)[1].split("\n## ", 1)[0]
        for name in model.model_fields:
            assert f"| `{name}` |" in part, f"[{section}] {name} missing"


def test_site_builds_strict(tmp_path: Path) -> None:
    """`mkdocs build --strict` succeeds; the API page documents all of sffscan.__all__ and
    the performance page holds every table bench/ wrote."""
    site = tmp_path / "site"
    done = _run("-m", "mkdocs", "build", "--strict", "--site-dir", site)
    assert done.returncode == 0, done.stderr[-4000:]
    import sffscan

    api = (site / "api" / "index.html").read_text(encoding="utf-8")
    for name in sffscan.__all__:
        if not name.startswith("__"):
            assert f"sffscan.{name}" in api, f"sffscan.{name} missing from the API page"
    perf = (site / "performance" / "index.html").read_text(encoding="utf-8")
    for table in (ROOT / "bench").glob("*.md"):
        assert f"bench/{table.name}" in perf, table.name
    assert 'class="mermaid"' in (site / "architecture" / "index.html").read_text(
        encoding="utf-8")


def test_readme_is_short_and_keeps_the_ci_command() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert ci.startswith("python3 -m venv .venv")
    assert f"\n{ci}\n" in readme, "the README's test command differs from .ci/run's"


def test_readme_links_resolve() -> None:
    """Every relative link of the README names a file of the repository."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme)
    local = [link for link in links if "://" not in link]
    assert local, "no relative links found"
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, missing


def test_pages_added_by_other_work_join_the_nav(tmp_path: Path) -> None:
    """docs/hooks.py puts printer-links, printjob* and depth-study pages into their nav
    sections when they exist, and leaves the nav alone when they do not."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("sffscan_docs_hooks", DOCS / "hooks.py")
    assert spec is not None and spec.loader is not None
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    nav = [{"Home": "index.md"}, {"Using sffscan": ["hardware.md"]},
           {"Methods and results": ["physics.md", "depth-study.md"]}]
    hooks.on_config({"nav": nav, "docs_dir": str(tmp_path)})
    assert nav[1] == {"Using sffscan": ["hardware.md"]}
    for name in ("printjob.md", "printer-links.md", "depth-study.md", "other.md"):
        (tmp_path / name).write_text("# x\n", encoding="utf-8")
    hooks.on_config({"nav": nav, "docs_dir": str(tmp_path)})
    assert nav[1] == {"Using sffscan": ["hardware.md", "printer-links.md", "printjob.md"]}
    assert nav[2] == {"Methods and results": ["physics.md", "depth-study.md"]}


def test_readme_command_table_has_every_command() -> None:
    """The README's command table names every sub-command of `sffscan --help`."""
    import argparse

    from sffscan.pipeline.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    table = readme.split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    missing = [c for c in sub.choices if f"| `sffscan {c}" not in table]
    assert not missing, f"README's command table lacks {missing}"
