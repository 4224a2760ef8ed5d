"""The ``lelsonar`` command line: one console script, one subcommand per job.

Each subcommand lives next to the code it drives, in a module that exposes
``register(subparsers)``.  That function adds its parser and sets ``run`` to a
callable taking the parsed arguments and returning an exit code.  Configuration
objects are built here, from flags and TOML, never at import time.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Modules that contribute subcommands, in the order `--help` lists them.
COMMAND_MODULES = (
    "lelsonar.commands",
    "lelsonar.acquire.cli",
    "lelsonar.acquire.sim.cli",
    "lelsonar.acquire.emulate.cli",
    "lelsonar.reconstruct.cli",
    "lelsonar.recordings.cli",
    "lelsonar.bridge.cli",
    "lelsonar.tools.demo",
    "lelsonar.tools.bench",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lelsonar",
        description="Robust plane estimates from a rotating ultrasonic array (LEL fitting of L-shaped corners).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from lelsonar.errors import LelsonarError

    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except LelsonarError as exc:
        print(f"lelsonar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
