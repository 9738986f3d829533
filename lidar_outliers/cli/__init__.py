"""`lidar-outliers`: the command line. Each module of this package adds one command.

A command module defines ``register(subparsers)``, which adds its parser and sets ``func`` (called
with the parsed arguments, returns the exit status). A module may also define
``split_argv(argv) -> (argv, extra)`` to take out arguments argparse cannot express (``detect``
uses it for ``--detector NAME --option ...`` groups); ``extra`` arrives as ``args.extra``.

Errors a user can cause end the program with one line ``lidar-outliers: error: <what>`` and
status 2 (usage, parameters) or 1 (input data); never a traceback (set LIDAR_OUTLIERS_DEBUG=1 to
see one for unexpected errors).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys
from collections.abc import Sequence
from types import ModuleType

from lidar_outliers.errors import LidarOutliersError, ParameterError

PROG = "lidar-outliers"
EXIT_DATA, EXIT_USAGE, EXIT_INTERRUPTED = 1, 2, 130


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (no usage dump)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        fail(message, EXIT_USAGE)


def fail(message: str, status: int) -> None:
    """Print ``lidar-outliers: error: <message>`` (one line) and exit with ``status``."""
    line = " ".join(str(message).split())
    sys.stderr.write(f"{PROG}: error: {line}\n")
    sys.exit(status)


#: The sub-commands, each a module of this package with ``register(subparsers)``.
COMMANDS = ("detect", "detectors", "simulate", "plot", "bench", "serve", "submit", "users")


def command_modules(only: str | None = None) -> dict[str, ModuleType]:
    """Sub-command modules by name (all of them, or just ``only`` when it names one).

    Importing one module only keeps start-up short: the service commands pull in modules that
    ``detect`` does not need.
    """
    names = [only] if only in COMMANDS else list(COMMANDS)
    return {name: importlib.import_module(f"{__name__}.{name}") for name in names}


def build_parser(modules: dict[str, ModuleType]) -> Parser:
    parser = Parser(
        prog=PROG,
        description="Outlier detection for mobile LiDAR point clouds (Leslar, Wang & Hu 2010).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for module in modules.values():
        module.register(sub)
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("lidar-outliers")
    except Exception:
        return "unknown"


def _split_command(argv: list[str], parser: Parser) -> str | None:
    """The sub-command named in argv (first token that is a known command)."""
    choices = set()
    for action in parser._subparsers._group_actions if parser._subparsers else []:
        choices |= set(getattr(action, "choices", {}) or {})
    return next((a for a in argv if a in choices), None)


def console_main() -> None:
    """The installed ``lidar-outliers`` command: ``main``, then exit with its status."""
    try:
        status = main()
    finally:
        # What is left at exit is freed by reference counting all the same; frozen, it is not
        # traversed again by the interpreter's final garbage collections (about 40 ms of every
        # short command's run time once pydantic and numpy are loaded). Not in ``main``: a
        # process that calls it (the tests) would keep its cyclic garbage for good.
        gc.freeze()
    sys.exit(status)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        first = next((a for a in argv if not a.startswith("-")), None)
        modules = command_modules(only=first)
        parser = build_parser(modules)
        command = _split_command(argv, parser)
        extra = None
        if command is not None:
            owner = modules[command]
            if hasattr(owner, "split_argv"):
                at = argv.index(command) + 1
                rest, extra = owner.split_argv(argv[at:])
                argv = argv[:at] + rest
        args = parser.parse_args(argv)
        args.extra = extra
        if not getattr(args, "func", None):
            parser.print_help(sys.stderr)
            return EXIT_USAGE
        return int(args.func(args) or 0)
    except ParameterError as exc:
        fail(str(exc), EXIT_USAGE)
    except LidarOutliersError as exc:
        fail(str(exc), EXIT_DATA)
    except KeyboardInterrupt:
        fail("interrupted", EXIT_INTERRUPTED)
    except BrokenPipeError:
        return EXIT_DATA
    except Exception as exc:
        if os.environ.get("LIDAR_OUTLIERS_DEBUG"):
            raise
        fail(f"internal error: {type(exc).__name__}: {exc}", EXIT_DATA)
    return EXIT_DATA


if __name__ == "__main__":
    console_main()
