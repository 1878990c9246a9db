"""Command line: ``sffscan demo | scan | config | schemas`` and the commands of
:data:`COMMAND_MODULES`.

Exit codes: 0 success; 1 a pipeline stage failed (its name and cause are printed, what was
already written stays readable); 2 bad configuration, bad input or bad usage; 3 the scan
ended cleanly but incomplete: fewer frames than expected (the plan's, or the count the
sender's end message gave) were received and processed, and the mosaic's status is
'incomplete' with both counts (``sffscan info MOSAIC`` shows them); 130
interrupted (Ctrl-C; the mosaic keeps what was completed, status 'failed', resumable); 143
terminated by SIGTERM (as Ctrl-C); 141 the output pipe was closed
by its reader (``sffscan info ... | head``), said nowhere.

Logging: ``-q`` (warnings and errors only, no progress display) and ``-v`` (debug lines
with their logger's names) go before or after the sub-command (``sffscan -q demo`` =
``sffscan demo -q``); :mod:`sffscan.pipeline.cli.logsetup` installs the one handler.
Results (summaries, reports, tables) go to stdout; status lines, warnings, errors and the
progress display to stderr.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import os
import re
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sffscan.pipeline.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    describe,
    fail,
    is_region,
    json_option,
    override,
    report_job,
    scan_options,
    viewer_sink,
)

if TYPE_CHECKING:
    from sffscan.pipeline.config import ScanConfig

log = logging.getLogger(__name__)

EXIT_PIPE_CLOSED = 141  # 128 + SIGPIPE, what a shell reports for a writer killed by it

#: Modules that add sub-commands; each defines ``register(sub)``.
COMMAND_MODULES: tuple[str, ...] = (
    "sffscan.pipeline.cli.record", "sffscan.pipeline.cli.hardware",
    "sffscan.pipeline.cli.calibrate", "sffscan.pipeline.cli.stack",
    "sffscan.pipeline.cli.metrology", "sffscan.pipeline.cli.batch",
    "sffscan.pipeline.cli.study", "sffscan.pipeline.cli.job", "sffscan.pipeline.cli.serve")


def _run(cfg: ScanConfig, args: argparse.Namespace, *, evaluate: bool, viewer_default: str) -> int:
    from sffscan.pipeline.run import Job

    log.info(describe(cfg))
    check = bool(getattr(args, "check", False))
    if check:
        from sffscan.pipeline.formats.exports import check_scan_exports

        for warning in check_scan_exports(cfg):
            log.warning("%s", warning)
    # pre-flight, clash checks and the writer lock before anything is created or deleted
    job = Job(cfg, source=getattr(args, "source", None), record=getattr(args, "record", None),
              rrd=args.rrd, progress=not args.quiet, check_only=check,
              sinks=lambda: [k for k in (viewer_sink(cfg, args.viewer, default=viewer_default,
                                                     rrd=args.rrd),) if k is not None])
    return report_job(job, evaluate=evaluate, as_json=bool(getattr(args, "json", False)))


DEMO_OUTPUT = "sffscan-demo.zarr"


def cmd_demo(args: argparse.Namespace) -> int:
    from sffscan.pipeline.config import REALISTIC_OPTICS, demo_config

    if args.output is None:  # the demo's own default output is replaced on every run
        args.output, args.overwrite = DEMO_OUTPUT, True
    optics = dict(REALISTIC_OPTICS) if getattr(args, "realistic", False) else {}
    cfg = override(demo_config(passes=args.passes, optics=optics), args)
    return _run(cfg, args, evaluate=True, viewer_default="auto")


def cmd_scan(args: argparse.Namespace) -> int:
    from sffscan.pipeline.config import load_config

    cfg = override(load_config(args.config), args)
    return _run(cfg, args, evaluate=not args.no_evaluate, viewer_default="off")


def cmd_config(args: argparse.Namespace) -> int:
    from sffscan.pipeline.config import config_to_toml, demo_config

    cfg = demo_config(passes=args.passes)
    text = config_to_toml(cfg)
    if args.output:
        from sffscan.pipeline.run import check_file_output

        try:  # never over a configuration already edited, unless asked
            check_file_output(args.output, "-o", overwrite=args.overwrite)
        except ValueError as err:
            return fail(str(err))
        Path(args.output).write_text(text, encoding="utf-8")
        log.info("wrote %s", args.output)
    else:
        print(text)
    return EXIT_OK


def cmd_schemas(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.schema_gen import (
        check_schemas,
        packaged_schema_dir,
        write_schemas,
    )

    folder = Path(args.dir) if args.dir is not None else packaged_schema_dir()
    which = "" if args.dir is not None else " (the packaged copy)"
    if args.check:
        stale = check_schemas(folder)
        if stale:
            print(f"schemas in {folder}{which} out of date: " + ", ".join(stale)
                  + " (run 'sffscan schemas" + (f" --dir {args.dir}'" if args.dir else "'")
                  + ")", file=sys.stderr)
            return EXIT_FAILED
        print(f"schemas in {folder}{which} up to date")
        return EXIT_OK
    for path in write_schemas(folder):
        print(f"wrote {path}")
    return EXIT_OK


COMPLETION_SHELLS = ("bash", "zsh", "tcsh")


def cmd_completion(args: argparse.Namespace) -> int:
    try:
        import shtab
    except ImportError:
        print("sffscan completion: needs the package 'shtab' (pip install shtab)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    print(shtab.complete(build_parser(), shell=args.shell))
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sffscan",
        description="Shape-from-focus in continuous motion: scan a part while it prints and "
                    "write a Zarr height mosaic.")
    parser.add_argument("--version", action=_VersionAction, help="print the version and exit")
    _log_options(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulated scan of the characterisation plate at 15 mm/s",
                       description="Simulated scan of the characterisation plate (thesis optics: "
                                   "1280x1024 px, 8.5 µm/px, 150 fps, N = 50, 15 mm/s), then "
                                   "the mosaic's accuracy against the true surface.")
    p.add_argument("--passes", type=int, default=1, help="parallel passes (default 1)")
    p.add_argument("--realistic", action="store_true",
                   help="real non-telecentric tunable-lens optics: +2 %% magnification over "
                        "the focus range, 150 µm field curvature at the corner, 20 %% "
                        "vignetting (default: ideal optics)")
    scan_options(p, output_help=f"mosaic path, a Zarr v3 group (default {DEMO_OUTPUT}, "
                                "replaced on every run)")
    json_option(p, "the summary")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("scan", help="run the pipeline from a TOML configuration",
                       description="Scan as a TOML configuration says (source, optics, "
                                   "motion, processing, output), with the options below "
                                   "overriding it, and write a Zarr height mosaic. "
                                   "'sffscan config' prints one to start from; --check "
                                   "tests it without scanning.")
    p.add_argument("--config", required=True, help="TOML file (see 'sffscan config')")
    p.add_argument("--no-evaluate", action="store_true",
                   help="skip the comparison with the simulated true surface")
    p.add_argument("--check", action="store_true",
                   help="check the configuration, device, paths and memory, then exit "
                        "without scanning (0 = ready, 2 = the error names the field)")
    scan_options(p, output_help="mosaic path, a Zarr v3 group (default: the "
                                "configuration's output.path)")
    json_option(p, "the summary")
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("config", help="print the demo configuration as TOML, to edit")
    p.add_argument("--passes", type=int, default=1,
                   help="parallel passes across the part (default 1)")
    p.add_argument("-o", "--output", help="write to this file instead of stdout")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing -o file (refused otherwise)")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("schemas", help="write (or --check) the JSON Schemas",
                       description="Write the JSON Schemas generated from the typed models, "
                                   "or --check that a folder holds them unchanged. Default "
                                   "folder: the installed package's copy (sffscan.schemas; "
                                   "the checkout's schemas/ in an editable install), "
                                   "whatever the current folder; the output names it.")
    p.add_argument("--dir", default=None,
                   help="schema folder (default: the packaged copy, sffscan.schemas)")
    p.add_argument("--check", action="store_true", help="fail if the files differ")
    p.set_defaults(func=cmd_schemas)

    p = sub.add_parser("completion", help="print a shell completion script (bash, zsh, tcsh)",
                       description="Print the completion script of a shell for every "
                                   "sffscan command and option (made by shtab). Bash: "
                                   "'sffscan completion bash > ~/.local/share/bash-completion/"
                                   "completions/sffscan'; zsh: 'sffscan completion zsh > "
                                   "~/.zfunc/_sffscan' with ~/.zfunc on fpath.")
    p.add_argument("shell", choices=COMPLETION_SHELLS, help="the shell: bash, zsh or tcsh")
    p.set_defaults(func=cmd_completion)
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(sub)
    for p in _sub_parsers(sub):  # -q / -v after the sub-command (and its own) too
        _log_options(p)
    _plain_texts(parser)
    return parser


_ROLE = re.compile(r":[a-z]+:`~?([^`<]+?)(?:\s*<[^>]*>)?`")
_LITERAL = re.compile(r"``(.+?)``", re.S)


def plain_text(text: str) -> str:
    """A docstring's reStructuredText as the terminal shows it: ``:mod:`x``` -> x,
    ````x```` -> 'x'."""
    return _LITERAL.sub(r"'\1'", _ROLE.sub(r"\1", text))


def _plain_texts(parser: argparse.ArgumentParser) -> None:
    """Descriptions and option help of every (sub-)command as plain text: a module
    docstring used as a description shows no reStructuredText markup."""
    if parser.description:
        parser.description = plain_text(parser.description)
    for action in parser._actions:
        if isinstance(action.help, str):
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _plain_texts(sub)


class _VersionAction(argparse.Action):
    """``--version``: the installed distribution's version, looked up only when asked for
    (importlib.metadata's look-up costs as much as the rest of the parser)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0,
                         help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        parser._print_message(f"sffscan {_version()}\n", sys.stdout)
        parser.exit()


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sffscan")
    except PackageNotFoundError:  # pragma: no cover - a source tree, not installed
        return "0+unknown"


def _sub_parsers(sub: Any) -> Iterator[argparse.ArgumentParser]:
    """Every parser under a sub-parsers action, nested ones (``calibrate z``, ``job
    show``) included."""
    for p in sub.choices.values():
        yield p
        for action in p._actions:  # argparse keeps its sub-commands only there
            if isinstance(action, argparse._SubParsersAction):
                yield from _sub_parsers(action)


def _log_options(p: argparse.ArgumentParser) -> None:
    """``-q`` / ``-v``; SUPPRESS defaults, so the sub-command's parser does not reset what
    was given before the sub-command (a sub-command that defines its own keeps it)."""
    for flags, kw in ((("-q", "--quiet"), {"action": "store_true",
                                           "help": "warnings and errors only; no progress "
                                                   "display"}),
                      (("-v", "--verbose"), {"action": "count",
                                             "help": "debug messages too, each with its "
                                                     "logger's name"})):
        try:
            p.add_argument(*flags, default=argparse.SUPPRESS, **kw)  # type: ignore[arg-type]
        except argparse.ArgumentError:
            pass


#: Options whose value may start with '-' (a box left of the origin):
#: ``--region -1299,-16,0,100`` (or ``-1mm,0,5mm,2mm``) is passed on as
#: ``--region=-1299,-16,0,100``, which argparse would otherwise take for an unknown option.
NEGATIVE_VALUE_OPTIONS = ("--region",)


def _joined_values(argv: Sequence[str]) -> list[str]:
    out: list[str] = []
    args = list(argv)
    i = 0
    while i < len(args):
        a = args[i]
        if a in NEGATIVE_VALUE_OPTIONS and i + 1 < len(args) and is_region(args[i + 1]):
            out.append(f"{a}={args[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _pipe_closed() -> int:
    """stdout's reader went away (``| head``): point stdout at /dev/null so that the
    interpreter's last flush is silent, and end without a message."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no real file descriptor (captured in tests)
        pass
    return EXIT_PIPE_CLOSED


def _subcommand_parser(parser: argparse.ArgumentParser, args: argparse.Namespace
                       ) -> argparse.ArgumentParser:
    """The innermost sub-command's parser that ``args`` came through (``sffscan job
    demo``: job's demo), or ``parser`` itself."""
    current = parser
    while True:
        subs = [a for a in current._actions if isinstance(a, argparse._SubParsersAction)]
        name = getattr(args, subs[0].dest, None) if subs and subs[0].dest else None
        if name is None or name not in subs[0].choices:
            return current
        current = subs[0].choices[name]


def parse_args(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args``, except that an unknown option is reported with the usage of
    the sub-command it was given to (argparse reports it with the top level's), with the
    closest option names."""
    args, extra = parser.parse_known_args(argv)
    if extra:
        where = _subcommand_parser(parser, args)
        known = [o for a in where._actions for o in a.option_strings]
        hints = []
        for word in extra:
            close = difflib.get_close_matches(word.split("=", 1)[0], known, n=2)
            if word.startswith("-") and close:
                hints.append(f"{word} (did you mean {' or '.join(close)}?)")
            else:
                hints.append(word)
        where.error(f"unrecognized arguments: {' '.join(hints)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = parse_args(build_parser(),
                          _joined_values(sys.argv[1:] if argv is None else argv))
        args.quiet = bool(getattr(args, "quiet", False))
        args.verbose = int(getattr(args, "verbose", 0) or 0)
        from sffscan.pipeline.cli.logsetup import cli_logging, level_for
        from sffscan.pipeline.config import ConfigError

        if argv is None:
            from sffscan.pipeline.heap import keep_freed_memory

            # the `sffscan` command's own process (not a caller's that runs main(argv)): its
            # stages (the thread placement's, the process placement's main process) reuse
            # freed memory as the workers' do (thread placement, 300 frames, 2 cores, six
            # pairs: 45.8-49.2 against 47.4-54.0 ms of CPU a frame)
            keep_freed_memory()

        from threadpoolctl import threadpool_limits

        # one BLAS thread, as the scan's runtime and its workers run: sffscan's matrix
        # products are per frame and small (a 640 x 512 frame's resampling 2.4 ms on both
        # of the 2-core VM's cores, 2.8 ms on one), and OpenBLAS's threads spin for each
        # other: with the other core busy the same resampling took 73-123 ms a frame
        # (`sffscan stopgo --realistic --calibration`: 8.5 s against 6.0-6.9 s)
        with cli_logging(level_for(quiet=args.quiet, verbose=args.verbose)), \
                threadpool_limits(limits=1, user_api="blas"):
            try:
                code = int(args.func(args))
            except BrokenPipeError:
                raise
            except (ConfigError, OSError) as err:  # bad configuration, or an unusable path
                print(f"sffscan: {err}", file=sys.stderr)
                code = EXIT_BAD_INPUT
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's last flush
        return code
    except BrokenPipeError:
        return _pipe_closed()


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
