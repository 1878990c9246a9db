"""Markdown field tables from a JSON Schema (shared by the generated reference pages).

Used by ``docs/gen_config_reference.py`` (the pydantic ``ScanConfig`` model's schema) and
``docs/gen_formats_reference.py`` (the files in ``schemas/``). Standard library only.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

Schema = dict[str, Any]


def _number(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() and abs(value) < 1e15 else f"{value:g}"
    return str(value)


def _cell(text: str) -> str:
    """Text safe inside a Markdown table cell (reStructuredText ``code`` made Markdown)."""
    return text.replace("``", "`").replace("|", "\\|").replace("\n", " ")


def _ref_name(ref: str) -> str:
    return ref.rsplit("/", 1)[-1]


def anchor(prefix: str, name: str) -> str:
    """The id of the heading that holds the table of ``$defs`` entry ``name``."""
    return f"{prefix}-{name}".lower().replace("_", "-").replace(".", "-")


def type_text(prop: Schema, *, link_refs: str | None = None) -> str:
    """A short type description of a schema property (``integer``, ``"sim" | "camera"``);
    ``$ref`` entries link to :func:`anchor` ``(link_refs, name)`` when ``link_refs`` is set."""
    if "$ref" in prop:
        name = _ref_name(prop["$ref"])
        return f"[{name}](#{anchor(link_refs, name)})" if link_refs else name
    if "const" in prop:
        return f"`{json.dumps(prop['const'], ensure_ascii=False)}`"
    if "enum" in prop:
        return " \\| ".join(f"`{json.dumps(v, ensure_ascii=False)}`" for v in prop["enum"])
    for key in ("anyOf", "oneOf"):
        if key in prop:
            parts = [type_text(p, link_refs=link_refs) for p in prop[key]
                     if p.get("type") != "null"]
            nullable = any(p.get("type") == "null" for p in prop[key])
            text = " or ".join(parts)
            return f"{text} or null" if nullable else text
    kind = prop.get("type")
    if kind == "array":
        if "prefixItems" in prop:
            inner = ", ".join(type_text(p, link_refs=link_refs) for p in prop["prefixItems"])
            return f"[{inner}]"
        if "items" in prop:
            return f"array of {type_text(prop['items'], link_refs=link_refs)}"
        return "array"
    if kind == "object":
        extra = prop.get("additionalProperties")
        if isinstance(extra, dict) and extra:
            return f"object of {type_text(extra, link_refs=link_refs)}"
        return "object"
    if isinstance(kind, list):
        return " or ".join(str(k) for k in kind)
    return str(kind) if kind else "any"


def range_text(prop: Schema) -> str:
    """The numeric bounds of a property (``>= 3, <= 255``), also inside ``anyOf``."""
    for key in ("anyOf", "oneOf"):
        if key in prop:
            found = [range_text(p) for p in prop[key]]
            return ", ".join(r for r in found if r)
    out = []
    for key, sign in (("minimum", ">="), ("exclusiveMinimum", ">"),
                      ("maximum", "<="), ("exclusiveMaximum", "<")):
        if key in prop:
            out.append(f"{sign} {_number(prop[key])}")
    for key, word in (("minItems", "items >="), ("maxItems", "items <=")):
        if key in prop and prop.get("minItems") != prop.get("maxItems"):
            out.append(f"{word} {prop[key]}")
    return ", ".join(out)


def default_text(prop: Schema, required: bool) -> str:
    if "default" not in prop:
        return "required" if required else ""
    value = prop["default"]
    if value is None:
        return "(not set)"
    if isinstance(value, (dict, list)) and len(json.dumps(value)) > 40:
        return "(see below)" if isinstance(value, dict) else "(list)"
    return f"`{json.dumps(value, ensure_ascii=False)}`"


def field_table(schema: Schema, *, link_refs: str | None = None,
                columns: tuple[str, ...] = ("key", "type", "default", "range",
                                            "meaning")) -> str:
    """A Markdown table with one row per property of an object schema."""
    required = set(schema.get("required", ()))
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for name, prop in schema.get("properties", {}).items():
        cells = {
            "key": f"`{name}`",
            "type": type_text(prop, link_refs=link_refs),
            "default": default_text(prop, name in required),
            "range": range_text(prop),
            "meaning": prop.get("description", ""),
        }
        lines.append("| " + " | ".join(_cell(cells[c]) if c == "meaning" else cells[c]
                                        for c in columns) + " |")
    return "\n".join(lines)


def defs_in_order(schema: Schema) -> list[tuple[str, Schema]]:
    """The ``$defs`` that are objects with properties, in the schema's order."""
    return [(name, sub) for name, sub in schema.get("$defs", {}).items()
            if sub.get("properties")]


def page_main(argv: list[str] | None, *, render: Callable[[], str], page: Path, source: str,
              script: str, description: str) -> int:
    """The command line of a generated page: write it, or ``--check`` that the committed
    page equals what ``render`` makes from ``source`` (exit 1, naming ``script``, if not)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--check", action="store_true",
                        help=f"exit 1 if the committed page differs from the {source}")
    parser.add_argument("--page", type=Path, default=page,
                        help=f"the page to write or check (default {page.name})")
    args = parser.parse_args(argv)
    text = render()
    out: Path = args.page
    if args.check:
        current = out.read_text(encoding="utf-8") if out.exists() else ""
        if current != text:
            print(f"{out}: out of date; run python docs/{script}", file=sys.stderr)
            return 1
        print(f"{out}: up to date")
        return 0
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out}")
    return 0
