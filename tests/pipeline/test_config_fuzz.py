"""Configuration fuzz (issue 13): every numeric field set to -1, 0, NaN, "x", 1e308 and
2^63-1 either passes every check ('sffscan scan --check') or exits 2 naming the field; never
a traceback, a hang or an out-of-memory. Cross-field checks run before anything is deleted."""

from __future__ import annotations

import json
import math
import types
import typing
from pathlib import Path
from typing import Any

import pytest
import zarr
from pydantic import BaseModel
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ConfigError, ScanConfig, config_from_dict, config_to_toml
from sffscan.pipeline.preflight import check_memory, memory_needed_bytes

FUZZ: tuple[Any, ...] = (-1, 0, float("nan"), "x", 1e308, 2**63 - 1)


def tiny(tmp: Path) -> dict[str, Any]:
    """A scan small enough to run: 160 x 64 px, N = 10, 8 mm."""
    return config_from_dict({
        "source": {"plate_length_mm": 12.0, "plate_width_mm": 2.0},
        "optics": {"width_px": 160, "height_px": 64, "pixel_um": 17.0, "n_levels": 10},
        "motion": {"x_start_mm": 1.0, "x_end_mm": 9.0},
        "processing": {"block_columns": 32, "registration_scale": 2},
        "output": {"chunk_px": 64, "path": str(tmp / "m.zarr")},
    }).model_dump(mode="json")


def _numeric(annotation: Any) -> bool:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Literal:
        return all(isinstance(a, int | float) and not isinstance(a, bool) for a in args)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_numeric(a) for a in args if a is not type(None))
    return annotation in (int, float)


def numeric_fields() -> list[tuple[str, str]]:
    """(table, field) of every numeric field of the configuration (top level: table '')."""
    out: list[tuple[str, str]] = []
    for name, info in ScanConfig.model_fields.items():
        ann = info.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out += [(name, k) for k, f in ann.model_fields.items() if _numeric(f.annotation)]
        elif _numeric(ann):
            out.append(("", name))
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def to_toml(data: dict[str, Any]) -> str:
    top = [f"{k} = {_toml_value(v)}" for k, v in data.items()
           if not isinstance(v, dict) and v is not None]
    lines = top + [""]
    for table, values in data.items():
        if isinstance(values, dict):
            lines.append(f"[{table}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in values.items() if v is not None]
    return "\n".join(lines) + "\n"


def test_every_numeric_field_is_covered_and_bounded() -> None:
    """Every numeric field has a range (both ends) in the model, so in the JSON Schema."""
    fields = numeric_fields()
    assert len(fields) >= 45
    schema = ScanConfig.model_json_schema()
    unbounded = []
    for table, name in fields:
        if table == "":
            continue
        node = schema["$defs"][ScanConfig.model_fields[table].annotation.__name__]  # type: ignore[union-attr]
        prop = node["properties"][name]
        options = prop.get("anyOf", [prop])
        nums = [o for o in options if o.get("type") in ("integer", "number")
                and "enum" not in o and "const" not in o]
        if nums and not all(("maximum" in o or "exclusiveMaximum" in o)
                            and ("minimum" in o or "exclusiveMinimum" in o) for o in nums):
            unbounded.append(f"{table}.{name}")
    assert unbounded == []


def test_fuzz_every_numeric_field_checks_or_exits_2_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = tiny(tmp_path)
    path = tmp_path / "fuzz.toml"
    accepted, refused = [], []
    for table, name in numeric_fields():
        for value in FUZZ:
            data = json.loads(json.dumps(base))
            (data[table] if table else data)[name] = value
            path.write_text(to_toml(data), encoding="utf-8")
            rc = main(["scan", "--config", str(path), "--check", "-q"])
            err = capsys.readouterr().err
            field = f"{table}.{name}" if table else name
            assert rc in (0, 2), f"{field} = {value!r}: exit {rc}\n{err}"
            if rc == 2:
                assert field in err or (table in err and name in err), \
                    f"{field} = {value!r}: the message does not name the field:\n{err}"
                refused.append(field)
            else:
                accepted.append((field, value))
    print(f"fuzz: {len(accepted) + len(refused)} cases, {len(refused)} refused naming the "
          f"field, {len(accepted)} accepted")
    assert not (tmp_path / "m.zarr").exists()  # --check creates nothing


def test_accepted_fuzz_values_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A sample of values that pass the checks really scans (exit 0), end to end."""
    base = tiny(tmp_path)
    for table, name, value in [("source", "seed", 0), ("optics", "z_min_um", -1),
                               ("motion", "y_start_mm", 0), ("optics", "noise_sigma", 0)]:
        data = json.loads(json.dumps(base))
        data[table][name] = value
        data["output"]["overwrite"] = True
        path = tmp_path / "run.toml"
        path.write_text(to_toml(data), encoding="utf-8")
        rc = main(["scan", "--config", str(path), "-q", "--no-evaluate"])
        assert rc == 0, capsys.readouterr().err


def test_a_non_utf8_file_and_a_huge_window_name_the_cause(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    bad = tmp_path / "latin1.toml"
    bad.write_bytes("[output]\npath = \"pi\xe8ce.zarr\"\n".encode("latin-1"))
    assert main(["scan", "--config", str(bad), "--check"]) == 2
    assert "not UTF-8" in capsys.readouterr().err
    data = tiny(tmp_path)
    data["processing"]["window"] = 101
    with pytest.raises(ConfigError, match=r"processing\.window = 101"):
        config_from_dict(data)


def test_memory_the_plan_needs_is_checked_naming_the_fields(tmp_path: Path) -> None:
    cfg = ScanConfig.model_validate(tiny(tmp_path))
    need = memory_needed_bytes(cfg)
    check_memory(cfg, available=10 * need)
    with pytest.raises(ConfigError, match=r"optics\.width_px .* processing\.queue_capacity"):
        check_memory(cfg, available=need)


def test_overwrite_deletes_nothing_before_the_checks_pass(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An existing complete mosaic survives --overwrite with a missing device or an unusable
    --record path: both are refused (exit 2) before anything is deleted."""
    data = tiny(tmp_path)
    path = tmp_path / "c.toml"
    path.write_text(to_toml(data), encoding="utf-8")
    assert main(["scan", "--config", str(path), "-q", "--no-evaluate"]) == 0
    before = dict(zarr.open_group(data["output"]["path"], mode="r").attrs)
    data["processing"].update(backend="torch", device="cuda:7")
    path.write_text(to_toml(data), encoding="utf-8")
    assert main(["scan", "--config", str(path), "-q", "--overwrite", "--no-evaluate"]) == 2
    assert "processing.device" in capsys.readouterr().err
    data["processing"].update(backend="opencv", device="cpu")
    path.write_text(to_toml(data), encoding="utf-8")
    assert main(["scan", "--config", str(path), "-q", "--overwrite", "--no-evaluate",
                 "--record", str(tmp_path / "no" / "such" / "rec.zarr")]) == 2
    assert "--record" in capsys.readouterr().err
    after = dict(zarr.open_group(data["output"]["path"], mode="r").attrs)
    assert after == before and after["status"] == "complete"
    # an existing path without --overwrite is refused by the same checks
    assert main(["scan", "--config", str(path), "-q", "--no-evaluate"]) == 2
    assert "output.path" in capsys.readouterr().err
    assert config_to_toml(ScanConfig.model_validate(data))  # still a valid configuration
