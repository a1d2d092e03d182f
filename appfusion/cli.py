"""The ``appfusion`` command line.

Each subcommand lives in its own module under :mod:`appfusion.commands` and defines
``register(subparsers)``, which adds its parser and sets ``func`` to a callable taking the parsed
arguments and returning an exit status. Modules are imported lazily by name, so adding a command
means adding one file and one line to :data:`COMMANDS`.

Errors a user can cause (:class:`~appfusion.errors.AppFusionError`, and an ``OSError`` about a named
file: no permission, disk full, a file where a folder goes) are printed as one line,
``appfusion: error: ...``, with exit status 2 and no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import AppFusionError

#: subcommand module names under appfusion.commands, in the order ``--help`` lists them
COMMANDS = ["info", "convert", "synth", "scan", "render", "bench", "gui", "devices", "record", "calibrate"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="appfusion",
        description="Capture an object's geometry and spatially varying BRDF with a depth camera, "
                    "a mirror ball and four printed white circles (AppFusion, Wu & Zhou 2015).")
    parser.add_argument("--version", action="version", version=f"appfusion {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"appfusion.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"appfusion.commands.{name}":
                continue  # that stage is not built yet
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except AppFusionError as e:
        print(f"appfusion: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.filename is None:
            raise                          # not about a file the user named: a traceback helps
        # a file system refusal (a file where a folder goes, no permission, disk full): one line
        where = e.filename if e.filename2 is None else f"{e.filename} -> {e.filename2}"
        print(f"appfusion: error: {where}: {e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("appfusion: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
