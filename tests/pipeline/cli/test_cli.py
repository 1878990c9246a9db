"""The command line at first contact: --version, -q/-v, logging instead of prints, a
closed output pipe, options a new user writes as the README shows them."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.cli.main import _joined_values, build_parser, main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.sim_source import simulate_frames

import sffscan
from tests.scan_helpers import small_config

ROOT = Path(__file__).resolve().parents[3]
SFFSCAN = [sys.executable, "-m", "sffscan"]


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"sffscan {sffscan.__version__}"
    assert sffscan.__version__ != "0+unknown"  # the installed distribution's version


@pytest.mark.parametrize("argv, shown", [
    (["config", "-o", "{p}"], True),
    (["-q", "config", "-o", "{p}"], False),  # -q before the sub-command ...
    (["config", "-o", "{p}", "-q"], False),  # ... or after it
])
def test_quiet_before_or_after_the_subcommand(argv: list[str], shown: bool, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c.toml"
    assert main([a.format(p=path) for a in argv]) == 0
    assert path.is_file()
    assert (f"wrote {path}" in capsys.readouterr().err) is shown


def test_config_never_replaces_an_edited_file_unless_asked(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c.toml"
    assert main(["config", "-o", str(path), "-q"]) == 0
    path.write_text(path.read_text() + "# my edits\n")
    assert main(["config", "-o", str(path), "-q"]) == 2
    assert f"-o {path}: exists; --overwrite replaces it" in capsys.readouterr().err
    assert path.read_text().endswith("# my edits\n")
    assert main(["config", "-o", str(path), "-q", "--overwrite"]) == 0
    assert not path.read_text().endswith("# my edits\n")


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_names_the_logger(where: str, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c.toml"
    argv = ["config", "-o", str(path)]
    assert main(["-v", *argv] if where == "before" else [*argv, "-v"]) == 0
    assert f"[sffscan.pipeline.cli.main] wrote {path}" in capsys.readouterr().err


def test_global_and_subcommand_quiet_parse_alike() -> None:
    p = build_parser()
    for argv in (["-q", "demo"], ["demo", "-q"]):
        assert p.parse_args(argv).quiet is True
    assert not hasattr(p.parse_args(["demo"]), "quiet")  # main() sets it False


def test_every_command_at_any_depth_takes_quiet_and_verbose_after_its_name() -> None:
    """``sffscan calibrate targets DIR -q`` was refused ("unrecognized arguments: -q") while
    the top-level help offers -q to every command: the nested commands (calibrate, job)
    lacked the options."""
    import argparse

    def commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
                 ) -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
        out = []
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out.append(((*path, name), sub))
                    out += commands(sub, (*path, name))
        return out

    found = commands(build_parser())
    assert {("calibrate", "targets"), ("job", "show")} <= {path for path, _ in found}
    for path, sub in found:
        flags = {f for a in sub._actions for f in a.option_strings}
        assert {"-q", "--quiet", "-v", "--verbose"} <= flags, " ".join(path)


def _stderr_prints(path: Path) -> list[int]:
    """Lines of ``print(..., file=sys.stderr)`` calls in a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    lines = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id == "print"):
            for kw in node.keywords:
                if kw.arg == "file" and "stderr" in ast.unparse(kw.value):
                    lines.append(node.lineno)
    return lines


def test_no_print_to_stderr_outside_the_command_line() -> None:
    """Warnings and status lines of the library go through logging (a program that imports
    sffscan routes or silences them); only pipeline/cli reports on stderr itself."""
    found = {}
    for folder in ("sffscan", "pipeline", "stages"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if rel.parts[:2] == ("pipeline", "cli"):
                continue
            lines = _stderr_prints(path)
            if lines:
                found[str(rel)] = lines
    assert found == {}
    # the check itself finds such a call
    probe = ROOT / "tests" / "__init__.py"
    assert _stderr_prints(probe) == []
    assert _stderr_prints(ROOT / "pipeline" / "cli" / "main.py")  # the CLI does report


@pytest.mark.parametrize("args", [["config"], ["--help"]])
def test_closed_output_pipe_ends_quietly(args: list[str]) -> None:
    """``sffscan config | head`` (the reader leaves first): no 'Broken pipe' message, no
    traceback; exit 141 (128 + SIGPIPE)."""
    proc = subprocess.Popen([*SFFSCAN, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before anything is written
    err = proc.stderr.read().decode()
    proc.stderr.close()
    code = proc.wait(timeout=60)
    assert "Broken pipe" not in err and "Traceback" not in err and "Exception" not in err, err
    assert code in (0, 141)  # 0 only where nothing was written at all


def test_info_into_head_says_nothing_about_the_pipe(tmp_path: Path) -> None:
    """The issue's case: ``sffscan info MOSAIC | head -1`` with more lines than head reads."""
    m = _mosaic(tmp_path, origin=(0, 0), shape=(8, 8))
    res = subprocess.run(["bash", "-c", f"'{sys.executable}' -m sffscan info '{m}' | head -1"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert res.stdout.startswith("mosaic ")
    assert "Broken pipe" not in res.stderr and "Traceback" not in res.stderr, res.stderr


def _mosaic(tmp_path: Path, *, origin: tuple[int, int], shape: tuple[int, int]) -> Path:
    rng = np.random.default_rng(1)
    h = rng.uniform(100.0, 900.0, shape).astype(np.float32)
    path = tmp_path / "m.zarr"
    w = MosaicWriter(path, origin_px=origin, shape=shape, pixel_um=8.5,
                     attrs={"focus_heights_um": [0.0, 500.0, 1000.0],
                            "processing": {"mode": "test"}})
    one = np.ones(shape, np.float32)
    w.write_region(*origin, {"height": h, "texture": 0.5 * one, "weight": one,
                             "confidence": one})
    w.set_status("complete")
    return path


def test_export_region_left_of_the_origin(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Demo mosaics start at negative world px: ``--region -1299,-16,0,100`` is a value."""
    m = _mosaic(tmp_path, origin=(-1310, -20), shape=(130, 1320))
    assert main(["export", str(m), "--region", "-1299,-16,0,100"]) == 0
    assert "region x -1299..0 y -16..100 px" in capsys.readouterr().out
    assert main(["compare", str(m), str(m), "--region", "-1299,-16,0,100"]) == 0
    assert "RMSE" in capsys.readouterr().out
    # only a box is joined: an option after --region stays an option
    assert _joined_values(["--region", "--json"]) == ["--region", "--json"]
    assert _joined_values(["--region", "-1,-2,3,4", "-q"]) == ["--region=-1,-2,3,4", "-q"]


def test_compare_without_tifffile_is_a_clear_error(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    m = _mosaic(tmp_path, origin=(0, 0), shape=(8, 8))
    ref = tmp_path / "ref.tif"
    ref.write_bytes(b"")
    monkeypatch.setitem(sys.modules, "tifffile", None)  # 'import tifffile' fails
    assert main(["compare", str(m), str(ref)]) == 2
    err = capsys.readouterr().err
    assert "ref.tif" in err and "'tifffile'" in err and "not installed" in err


def test_replay_hint_names_the_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.pipeline.formats.test_recording import plain_recording

    cfg = small_config(motion={"x_end_mm": 6.0})
    frames = [f for _, f in zip(range(8), simulate_frames(cfg), strict=False)]
    rec = tmp_path / "rec.zarr"
    plain_recording(rec, cfg, frames)
    out = tmp_path / "m.zarr"
    out.mkdir()
    assert main(["replay", str(rec), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "--overwrite" in err and "set output.overwrite" not in err


def test_replay_takes_the_viewer_as_one_word() -> None:
    """``replay --viewer off rec.zarr -o m.zarr``: 'rec.zarr' is the recording, not a
    second viewer word; ``save`` takes its path from --rrd."""
    args = build_parser().parse_args(["replay", "--viewer", "off", "rec.zarr", "-o", "m.zarr"])
    assert args.viewer == "off" and args.recording == "rec.zarr"
    args = build_parser().parse_args(["demo", "--viewer", "save", "--rrd", "a.rrd"])
    assert (args.viewer, args.rrd) == ("save", "a.rrd")


def test_viewer_words(tmp_path: Path) -> None:
    from sffscan.pipeline.cli.common import viewer_mode
    from sffscan.pipeline.config import ConfigError

    assert viewer_mode(None, None, default="auto") == ["auto"]
    assert viewer_mode("serve", None) == ["serve"]
    assert viewer_mode(None, "a.rrd") == ["save", "a.rrd"]  # --rrd alone: save
    assert viewer_mode("save", "a.rrd") == ["save", "a.rrd"]
    with pytest.raises(ConfigError, match="--rrd PATH"):
        viewer_mode("save", None)
    with pytest.raises(ConfigError, match="only with --viewer save"):
        viewer_mode("serve", "a.rrd")


def test_scan_header_thesis_limit_agrees_with_plan(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Same optics, same overlap (motion.pass_overlap): the same thesis per-stack limit."""
    import re

    cfg = small_config(motion={"pass_overlap": 0.091, "x_end_mm": 6.0})
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    assert main(["plan", "--config", str(toml)]) == 0
    plan_out = capsys.readouterr().out
    plan_limit = float(re.search(r"max speed, mm/s\s+([\d.]+)", plan_out).group(1))  # type: ignore[union-attr]
    assert "overlap 9.1 %" in plan_out
    assert main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "-q",
                 "--no-evaluate", "-v"]) == 0
    header = capsys.readouterr().err
    got = re.search(r"thesis per-stack limit ([\d.]+) mm/s \(overlap 9.1 %", header)
    assert got is not None, header
    assert float(got.group(1)) == pytest.approx(plan_limit, abs=0.051)  # both rounded
    # and the figure is the thesis' eq. 6.1-6.3 with that overlap, not without it
    w_mm = 640 * 17.0 / 1000
    assert plan_limit == pytest.approx(150 / 50 * w_mm * (1 - 0.091) / 2, abs=0.006)


def test_packaged_schemas_checked_from_any_folder(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from sffscan.pipeline.formats.schema_gen import packaged_schema_dir

    monkeypatch.chdir(tmp_path)  # no schemas/ here
    main(["schemas", "--check"])
    text = capsys.readouterr()
    where = str(packaged_schema_dir())
    assert f"schemas in {where} (the packaged copy)" in text.out + text.err
    assert (Path(where) / "scan_config.v1.json").is_file()
    # --dir still writes and checks a given folder
    assert main(["schemas", "--dir", "out"]) == 0
    assert main(["schemas", "--dir", "out", "--check"]) == 0
    assert "schemas in out up to date" in capsys.readouterr().out
    (tmp_path / "out" / "frame_header.v1.json").write_text("{}")
    assert main(["schemas", "--dir", "out", "--check"]) == 1
    assert "frame_header.v1.json" in capsys.readouterr().err



def test_batch_takes_the_same_processing_choices_as_replay() -> None:
    """`batch` offers the processing options of `replay` (it had its own copy, limited to
    GLVM and TENV)."""
    from sffscan.pipeline.cli.main import build_parser

    parser = build_parser()
    for command in (["batch", "layers", "-o", "out"], ["replay", "rec.zarr", "-o", "m.zarr"]):
        args = parser.parse_args([*command, "--operator", "LAPM", "--method", "wcentroid"])
        assert (args.operator, args.method) == ("lapm", "wcentroid")


def test_the_command_line_keeps_freed_memory_as_the_workers_do(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The `sffscan` command's own process (main() without arguments, as the console script
    calls it) takes the workers' glibc heap settings
    (:func:`sffscan.pipeline.heap.keep_freed_memory`) before it runs anything; main(argv),
    called from another program, leaves that program's process alone."""
    import sffscan.pipeline.heap as heap

    calls: list[int] = []
    monkeypatch.setattr(heap, "keep_freed_memory", lambda: calls.append(1) or True)
    assert main(["config"]) == 0
    assert calls == []
    monkeypatch.setattr(sys, "argv", ["sffscan", "config"])
    assert main() == 0
    assert "[optics]" in capsys.readouterr().out
    assert calls == [1]


@pytest.mark.parametrize("argv", [["calibrate", "sim"], ["demo"], ["stopgo"], ["twostep"],
                                  ["job", "demo"], ["calibrate", "targets", "t"]])
def test_every_seed_is_a_non_negative_integer_or_a_usage_error(
        argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """``calibrate sim --seed -5`` raised numpy's ValueError (a traceback, exit 1)."""
    for bad, words in (("-5", "a seed is a non-negative integer, got -5"),
                       ("x", "not an integer: 'x'")):
        with pytest.raises(SystemExit) as info:
            main([*argv, "--seed", bad])
        assert info.value.code == 2
        assert f"argument --seed: {words}" in capsys.readouterr().err


def test_a_command_runs_with_one_blas_thread_and_gives_the_callers_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # OpenBLAS's threads spin for each other: with the other core busy a frame's resampling
    # took 73-123 ms against 5 ms on one thread (pipeline/cli/main.py); a command runs as
    # the scan's runtime does, and a caller's own setting is back after main() returns
    import sffscan.pipeline.config as config
    from threadpoolctl import threadpool_info, threadpool_limits

    seen: list[int] = []
    original = config.demo_config

    def recording(**kwargs: object) -> object:
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
        return original(**kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(config, "demo_config", recording)
    with threadpool_limits(limits=2, user_api="blas"):
        assert main(["-q", "config", "-o", str(tmp_path / "c.toml")]) == 0
        after = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert seen and set(seen) == {1}
    assert set(after) == {2}
