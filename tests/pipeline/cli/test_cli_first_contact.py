"""First contact, second round (issue 26: items 9, 10, 11, 18 and 23's leftover): hints that
name a command that works, regions in mm, readable ``info``, help on every option, ``--json``
for scripts, a light ``--help``, the public API's names."""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import _joined_values, build_parser, main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.sim_source import simulate_frames

import sffscan
from tests.pipeline.formats.test_transport import tiny_config
from tests.scan_helpers import small_config

ROOT = Path(__file__).resolve().parents[3]


def _walk(parser: argparse.ArgumentParser, prog: str = "sffscan"
          ) -> list[tuple[str, argparse.ArgumentParser]]:
    out = [(prog, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += _walk(sub, f"{prog} {name}")
    return out


def _recording(tmp_path: Path, n: int = 12) -> Path:
    """A complete recording (format 4: each frame's digest in its header copy) of the first
    ``n`` frames of a tiny simulated scan, made by sffscan's own writer."""
    from sffscan.pipeline.completeness import FrameAccount
    from sffscan.pipeline.formats.recording_writer import RecordingWriter

    cfg = tiny_config()
    tmp_path.mkdir(parents=True, exist_ok=True)
    rec = tmp_path / "rec.zarr"
    writer = RecordingWriter(rec, cfg, account=FrameAccount(planned=n))
    for _, f in zip(range(n), simulate_frames(cfg), strict=False):
        writer.write(f)
    writer.close()
    return rec


def _mosaic(tmp_path: Path) -> Path:
    rng = np.random.default_rng(1)
    shape = (16, 24)
    h = rng.uniform(100.0, 900.0, shape).astype(np.float32)
    h[:4, :] = np.nan  # 96 of 384 px without a height
    path = tmp_path / "m.zarr"
    w = MosaicWriter(path, origin_px=(-8, 0), shape=shape, pixel_um=8.5,
                     attrs={"focus_heights_um": [0.0, 500.0, 1000.0],
                            "processing": {"focus_operator": "glvm", "window": 9,
                                           "depth_method": "adaptive", "registration": True,
                                           "backend": "opencv"}})
    one = np.ones(shape, np.float32)
    w.write_region(-8, 0, {"height": h, "texture": 0.5 * one, "weight": one,
                           "confidence": one})
    w.set_status("complete")
    return path


# ------------------------------------------------------------------------- 9: hints


def test_spawn_without_display_hints_a_command_that_works(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(small_config(motion={"x_end_mm": 6.0})))
    code = main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "--viewer",
                 "spawn", "--no-evaluate", "-q"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--viewer save PATH" not in err  # refused by the parser: not a hint
    assert "--viewer serve" in err and "--rrd PATH" in err
    # and the hinted command parses
    build_parser().parse_args(["scan", "--config", "x.toml", "--rrd", "PATH.rrd"])


def test_odd_window_error_says_got_once(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--window", "8", "-q"]) == 2
    err = capsys.readouterr().err
    assert "processing.window" in err and "must be odd" in err
    assert err.count("got 8") == 1, err
    assert "Value error," not in err


@pytest.mark.parametrize("argv, usage, hint", [
    (["demo", "--windw", "9"], "usage: sffscan demo", "--window"),
    (["info", "x.zarr", "--verfy"], "usage: sffscan info", "--verify"),
    (["job", "demo", "--layrs", "2"], "usage: sffscan job demo", "--layers"),
])
def test_misspelt_option_shows_the_subcommands_usage(
        argv: list[str], usage: str, hint: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(usage), err
    assert f"did you mean {hint}" in err


def test_resume_of_a_complete_mosaic_is_not_an_error(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    rec = _recording(tmp_path)
    out = tmp_path / "m.zarr"
    assert main(["replay", str(rec), "-o", str(out), "-q"]) == 0
    capsys.readouterr()
    assert main(["replay", str(rec), "-o", str(out), "--resume", "-q"]) == 0
    err = capsys.readouterr().err
    assert "complete already" in err
    assert zarr.open_group(str(out), mode="r").attrs["status"] == "complete"
    # another recording's complete mosaic is still refused, naming it
    other = _recording(tmp_path / "other", n=10)
    assert main(["replay", str(other), "-o", str(out), "--resume", "-q"]) == 2
    assert "cannot resume from the recording" in capsys.readouterr().err


# ------------------------------------------------------------------------- 10: regions, info


@pytest.mark.parametrize("text, box", [
    ("1mm,0,5mm,2mm", (117, 0, 589, 236)),  # 8.5 µm/px: 1000/8.5 = 117.6 -> down, 588.2 up
    ("0,0,10,20", (0, 0, 10, 20)),
    ("-1299,-16,0,100", (-1299, -16, 0, 100)),
    ("-17um,0µm,85µm,8.5um", (-2, 0, 10, 1)),
    ("10px,0px,20px,4", (10, 0, 20, 4)),
    ("0.5mm, 0 , 1mm ,0.1mm", (58, 0, 118, 12)),
])
def test_region_takes_units(text: str, box: tuple[int, int, int, int]) -> None:
    from sffscan.pipeline.cli.common import parse_region

    assert parse_region(text, pixel_um=8.5) == box


@pytest.mark.parametrize("text, words", [
    ("1,2,3", "four coordinates"), ("1in,0,2in,1in", "four coordinates"),
    ("1.5,0,3,4", "whole number"), ("5mm,0,1mm,1mm", "empty box"),
    ("0,0,1e400,10", "1e400: not a finite number"), ("0,-1e999mm,1,1", "not a finite"),
])
def test_region_errors_name_the_option(text: str, words: str) -> None:
    from sffscan.pipeline.cli.common import parse_region

    with pytest.raises(ValueError, match="--region") as info:
        parse_region(text, pixel_um=8.5)
    assert words in str(info.value)


def test_negative_region_with_units_is_a_value() -> None:
    assert _joined_values(["--region", "-1mm,0,5mm,2mm", "-q"]) == ["--region=-1mm,0,5mm,2mm",
                                                                   "-q"]
    assert _joined_values(["--region", "--json"]) == ["--region", "--json"]


def test_info_mosaic_is_readable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sffscan.pipeline.metrology.evaluate import Accuracy, store_accuracy

    m = _mosaic(tmp_path)
    store_accuracy(m, Accuracy(rmse_um=3.25, corr=0.9991, psnr_db=48.5, pixels=288,
                               coverage=0.75, within_2sigma=0.9375, sigma_pixels=288),
                   truth="test")
    assert main(["info", str(m)]) == 0
    out = capsys.readouterr().out
    assert "{'" not in out and "': " not in out, out  # no Python dict
    assert "processing  glvm k=9, adaptive, registration on, backend opencv" in out
    assert "valid       288 px with a height (75.0 % of 384)" in out
    h = np.asarray(zarr.open_group(str(m), mode="r")["height"])
    assert f"height      {np.nanmin(h):.1f} .. {np.nanmax(h):.1f} µm" in out
    assert ("accuracy    RMSE 3.2 µm, CORR 0.9991, PSNR 48.5 dB over 288 px (stored; against "
            "test)") in out
    assert "uncertainty 93.8 % of 288 px within 2 sigma of that truth (calibrated: 90-98 %)" in out
    assert main(["info", str(m), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["valid_pixels"] == 288 and got["accuracy"]["rmse_um"] == 3.25
    assert got["height_range"]["min_um"] == pytest.approx(float(np.nanmin(h)))
    assert got["processing"]["depth_method"] == "adaptive"


# ------------------------------------------------------------------------- 11: help texts

_RST = re.compile(r":(func|class|mod|data|meth|attr|exc|obj):`|``")


def test_every_option_has_help_without_rst() -> None:
    missing, rst = [], []
    for prog, parser in _walk(build_parser()):
        texts = [parser.description or ""]
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction) or a.help == argparse.SUPPRESS:
                continue
            name = "/".join(a.option_strings) or a.dest
            if not (a.help or "").strip():
                missing.append(f"{prog} {name}")
            texts.append(a.help or "")
        rst += [f"{prog}: {m.group(0)}" for t in texts for m in _RST.finditer(t)]
    assert not missing and not rst, ("options without help:\n" + "\n".join(missing)
                                     + "\nraw reStructuredText in help:\n" + "\n".join(rst))


def test_scan_output_help_is_its_own() -> None:
    parsers = dict(_walk(build_parser()))
    helps = {prog: next(str(a.help) for a in parsers[prog]._actions if "-o" in a.option_strings)
             for prog in ("sffscan scan", "sffscan demo")}
    assert "demo" not in helps["sffscan scan"] and "output.path" in helps["sffscan scan"]
    assert "sffscan-demo.zarr" in helps["sffscan demo"]


# ------------------------------------------------------------------------- 18: scripting


def test_plan_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["fps"] == 150.0 and got["n_levels"] == 50
    assert got["sliding"]["max_speed_mm_s"] > got["thesis"]["max_speed_mm_s"] > 0
    assert got["thesis"]["total_time_s"] >= got["thesis"]["scan_time_s"]


def test_replay_and_info_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = _recording(tmp_path)
    assert main(["replay", str(rec), "-o", str(tmp_path / "m.zarr"), "-q", "--json"]) == 0
    out = capsys.readouterr().out
    got = json.loads(out)  # the whole of stdout is one JSON object
    assert got["mosaic"] == str(tmp_path / "m.zarr") and got["frames"] == 12
    assert got["account"]["complete"] is True and got["dropped"] == 0
    assert {s["name"] for s in got["stages"]} >= {"source"}
    assert main(["info", str(rec), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "recording" and info["report"]["frames"] == 12
    assert info["defects"] == 0 and info["processing"]["window"] == tiny_config().processing.window


def test_parser_construction_imports_nothing_heavy() -> None:
    code = ("import sys; from sffscan.pipeline.cli.main import build_parser; build_parser(); "
            "print(sorted(m for m in ('zarr', 'torch', 'rerun', 'xarray', 'dask', 'tqdm', "
            "'shtab', 'sffscan.pipeline.formats.recording') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120, cwd=ROOT)
    assert res.stdout.strip() == "[]"


def test_import_sffscan_loads_only_the_standard_library() -> None:
    code = ("import sys, sffscan; "
            "print(sorted(m for m in ('numpy', 'pydantic', 'zarr', 'sffscan.pipeline.config', "
            "'sffscan.api') if m in sys.modules)); print(sffscan.__version__)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120, cwd=ROOT)
    loaded, version = res.stdout.splitlines()
    assert loaded == "[]"
    assert version == sffscan.__version__ != "0+unknown"


def test_public_api_has_export_areal_and_batch() -> None:
    for name in ("areal_parameters", "ArealParameters", "read_region", "write_ply",
                 "write_x3p", "run_batch", "find_recordings", "BatchRow"):
        assert name in sffscan.__all__
        assert callable(getattr(sffscan, name))
    p = sffscan.areal_parameters(np.arange(16.0).reshape(4, 4), level="mean")
    assert p.sa_um == pytest.approx(4.0)


# ------------------------------------------------------------------------- 23: info --verify


def test_info_verify_fails_on_misplaced_frames(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    rec = _recording(tmp_path)
    assert main(["info", str(rec), "--verify"]) == 0
    capsys.readouterr()
    f3, f5 = rec / "frames" / "c.3.0.0", rec / "frames" / "c.5.0.0"
    a, b = f3.read_bytes(), f5.read_bytes()
    f3.write_bytes(b)
    f5.write_bytes(a)
    assert main(["info", str(rec), "--verify"]) == 3
    err = capsys.readouterr().err
    assert "misplaced frame_id" in err and "3" in err and "5" in err
    shutil.rmtree(rec)


def test_bash_completion_completes_commands_and_options(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    assert main(["completion", "bash"]) == 0
    script = tmp_path / "sffscan.bash"
    script.write_text(capsys.readouterr().out)
    bash = shutil.which("bash")
    assert bash is not None
    probe = (f"source '{script}'; "
             "COMP_WORDS=(sffscan rep); COMP_CWORD=1; _shtab_sffscan; echo \"${COMPREPLY[@]}\"; "
             "COMP_WORDS=(sffscan info --ver); COMP_CWORD=2; _shtab_sffscan; "
             "echo \"${COMPREPLY[@]}\"")
    res = subprocess.run([bash, "-c", probe], capture_output=True, text=True, timeout=60,
                         check=True)
    assert res.stdout.splitlines() == ["replay", "--verify --verbose"], res.stdout
    assert main(["completion", "zsh"]) == 0
    assert "#compdef sffscan" in capsys.readouterr().out


def test_json_values_are_plain() -> None:
    from sffscan.pipeline.cli.common import plain_json

    got = plain_json({"n": np.int64(3), "x": np.float32(1.5), "ok": np.bool_(True),
                      "path": Path("/m.zarr"), "box": (1, 2)})
    assert got == {"n": 3, "x": 1.5, "ok": True, "path": "/m.zarr", "box": [1, 2]}
    assert type(got["n"]) is int and type(got["ok"]) is bool
