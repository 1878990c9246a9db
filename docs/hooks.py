"""MkDocs hook: the API reference of ``sffscan.__all__`` and the ``bench/`` result tables.

The line ``<!-- sffscan-api-reference -->`` in a page becomes one mkdocstrings block per
public name, so the reference follows ``sffscan.__all__`` without a hand-kept list. Each
block names the object by the file that defines it (``pipeline/config.py`` ->
``pipeline.config``): the package maps top-level folders into ``sffscan`` (pyproject's
package-dir), which griffe cannot follow from the name ``sffscan.pipeline.config``, so the
site searches the repository root (``paths: [.]`` in mkdocs.yml).

The line ``<!-- bench-result-tables -->`` becomes the list of ``bench/*.py`` scripts (the
first paragraph of each docstring) and every ``bench/*.md`` and ``bench/results/*.md``
table as its script last wrote
it, headings moved two levels down: the figures are never copied by hand.

Pages other work adds (:data:`OPTIONAL_PAGES`) join their nav section when they exist.
"""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path
from typing import Any

MARKER = "<!-- sffscan-api-reference -->"
BENCH_MARKER = "<!-- bench-result-tables -->"

#: nav section -> page patterns added to it when such pages exist and are not in the nav
OPTIONAL_PAGES = {
    "Using sffscan": ("printer-links.md", "printjob*.md"),
    "Methods and results": ("depth-study.md",),
}
ROOT = Path(__file__).resolve().parent.parent


def _griffe_path(obj: Any, name: str) -> str:
    """The dotted path griffe finds ``obj`` at, searching the repository root: the module's
    own name where the repository holds it so (``sffscan/api.py``), else without the
    ``sffscan.`` the package-dir mapping adds (``sffscan.pipeline.config`` is
    ``pipeline/config.py``). Independent of how the package is installed."""
    module = getattr(obj, "__module__", None)
    if not module:
        raise ValueError(f"sffscan.{name}: cannot tell which module defines it")
    parts = module.split(".")
    for cand in (parts, parts[1:]):
        base = ROOT.joinpath(*cand)
        if cand and (base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()):
            return ".".join([*cand, obj.__name__])
    return f"{module}.{obj.__name__}"


def api_blocks() -> str:
    """Markdown: a heading per kind and a mkdocstrings block per public name."""
    sffscan = importlib.import_module("sffscan")
    names = [n for n in sffscan.__all__ if not n.startswith("__")]
    objects = {n: getattr(sffscan, n) for n in names}
    groups = {
        "Functions": [n for n in names if inspect.isfunction(objects[n])],
        "Exceptions": [n for n in names if inspect.isclass(objects[n])
                       and issubclass(objects[n], BaseException)],
    }
    groups["Classes"] = [n for n in names if inspect.isclass(objects[n])
                         and n not in groups["Exceptions"]]
    others = [n for n in names if not any(n in g for g in groups.values())]
    if others:
        raise ValueError(f"sffscan.__all__: no API reference for {others}")
    out = []
    for title, group in groups.items():
        if not group:
            continue
        out.append(f"### {title}\n")
        for name in group:
            out.append(f"::: {_griffe_path(objects[name], name)}\n"
                       f"    options:\n"
                       f'      heading: "sffscan.{name}"\n'
                       f'      toc_label: "{name}"\n')
    return "\n".join(out)


def _demote(text: str, levels: int) -> str:
    """``text`` with every Markdown heading outside code fences ``levels`` deeper."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            line = "#" * levels + line
        out.append(line)
    return "\n".join(out)


def bench_tables() -> str:
    """Markdown: the benchmark scripts and their last result tables."""
    bench = ROOT / "bench"
    out = ["| script | what it measures |", "|---|---|"]
    for script in sorted(bench.glob("bench_*.py")):
        doc = ast.get_docstring(ast.parse(script.read_text(encoding="utf-8"))) or ""
        first = " ".join(doc.split("\n\n")[0].split()).replace("|", "\\|")
        out.append(f"| `python bench/{script.name}` | {first} |")
    out.append("")
    for table in sorted(bench.glob("*.md")) + sorted(bench.glob("results/*.md")):
        out.append(f"## `bench/{table.relative_to(bench).as_posix()}`\n")
        out.append(_demote(table.read_text(encoding="utf-8"), 2) + "\n")
    return "\n".join(out)


def _listed(nav: Any) -> set[str]:
    if isinstance(nav, str):
        return {nav}
    if isinstance(nav, list):
        return set().union(*(_listed(item) for item in nav)) if nav else set()
    if isinstance(nav, dict):
        return set().union(*(_listed(v) for v in nav.values())) if nav else set()
    return set()


def on_config(config: Any, **kwargs: Any) -> Any:
    nav = config["nav"]
    if not nav:
        return config
    docs = Path(config["docs_dir"])
    listed = _listed(nav)
    for section, patterns in OPTIONAL_PAGES.items():
        pages = sorted({p.relative_to(docs).as_posix() for pattern in patterns
                        for p in docs.glob(pattern)} - listed)
        if not pages:
            continue
        for item in nav:
            if isinstance(item, dict) and isinstance(item.get(section), list):
                item[section].extend(pages)
                break
        else:
            raise ValueError(f"mkdocs.yml: no nav section {section!r} for {pages}")
    return config


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    if MARKER in markdown:
        markdown = markdown.replace(MARKER, api_blocks())
    if BENCH_MARKER in markdown:
        markdown = markdown.replace(BENCH_MARKER, bench_tables())
    return markdown
