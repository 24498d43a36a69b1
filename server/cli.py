"""The ``mocap`` command line: one parser, one module per subcommand.

Each module in ``server.commands`` exposes ``register(subparsers)``; the parser it adds
carries ``func`` (args -> exit code). ``mocap client`` runs the client package in its own
interpreter so that ``server`` never imports ``client``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from common.argtypes import OneLineParser

EXIT_OK = 0
EXIT_USAGE = 2  # bad input: missing/corrupt files, bad calibration, wrong arguments
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT), as a shell reports it
ACTION_DESTS = ("calib_command", "config_command", "bench")  # the commands' own subcommands

COMMAND_MODULES = (
    "calib", "synth", "fit", "server", "keys", "bench", "segment", "import_video", "voxels", "live", "export",
    "report", "run", "batch", "config", "demo", "sync",
)


def _client_entry(argv: list[str]) -> int:
    os.execv(sys.executable, [sys.executable, "-m", "client", *argv])
    return EXIT_OK  # not reached


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="mocap", description="Markerless multi-view silhouette motion capture.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"server.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"server.commands.{name}":
                continue  # optional subcommand not installed in this build
            raise
        module.register(sub)
    client = sub.add_parser("client", help="run a limb-fitting client (same as python -m client)",
                            add_help=False)
    client.set_defaults(func=None)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "client":
        return _client_entry(argv[1:])
    parser = build_parser()
    try:
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # said by the command's own parser: "mocap fit: error: ...", its --help named
            _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    except SystemExit as exc:  # --help, or a bad option (already said in one line)
        return int(exc.code or EXIT_OK)
    from common.errors import UserError
    from common.argtypes import one_line

    # what the messages name: the command and its action where it has one ("calib convert")
    name = " ".join(str(v) for v in (args.command, *(getattr(args, a, None) for a in ACTION_DESTS)) if v)

    try:
        if hasattr(args, "command_parser") and (args.config is not None or args.preset is not None or args.set):
            # a preset's, a Config.toml's and --set's values become the command's defaults; options given win
            from server.config import fit_option_defaults

            args.command_parser.set_defaults(**fit_option_defaults(args.preset, args.config, args.set))
            args = parser.parse_args(argv)
        return int(args.func(args) or EXIT_OK)
    except UserError as exc:
        print(f"mocap {name}: error: {one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # the reader stopped reading (mocap config show | head): nothing to say
        try:  # and no second error as the interpreter flushes stdout at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):  # stdout is no file (captured): nothing will flush to a pipe
            pass
        return 1
    except OSError as exc:  # the disk, not the input: full, read-only, a folder where a file goes
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"mocap {name}: error: {one_line(where + str(exc.strerror or exc))}", file=sys.stderr)
        return EXIT_USAGE
    except (KeyboardInterrupt, SystemError) as exc:
        # Ctrl-C while a compiled (numba) loop runs arrives as that loop returns, as a
        # SystemError ("returned a result with an exception set") whose context is the interrupt
        if not _interrupted(exc):
            raise
        from server.results import stopped_note

        kept = (f"; {stopped_note(args.out)}" if args.command in ("fit", "server")
                else "; what was done is kept, and the same command again goes on from there"
                if args.command in ("run", "batch") else "")
        print(f"mocap {name}: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED


def _command_parser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The parser of the (sub)command ``args`` were parsed for: "calib convert"'s, "fit"'s."""
    for dest in ("command", *ACTION_DESTS):
        chosen = getattr(args, dest, None)
        for action in parser._actions:  # argparse keeps the subcommands' parsers there only
            if isinstance(action, argparse._SubParsersAction) and action.dest == dest and chosen in action.choices:
                parser = action.choices[chosen]
    return parser


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` was raised while handling a KeyboardInterrupt (its causes and contexts)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
