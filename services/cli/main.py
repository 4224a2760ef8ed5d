"""The ``lelsonar`` command line: one console script, one subcommand per job.

Each subcommand is a module of this package (``lelsonar bench`` is the thin entry over
``tools/``) that exposes ``register(subparsers)``.  That function adds its parser and sets ``run`` to a
callable taking the parsed arguments and returning an exit code.  Configuration
objects are built here, from flags and TOML, never at import time.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Modules that contribute subcommands, in the order `--help` lists them.
COMMAND_MODULES = (
    "lelsonar.cli.contract",
    "lelsonar.cli.secure",
    "lelsonar.cli.acquire",
    "lelsonar.cli.simulate",
    "lelsonar.cli.emulate",
    "lelsonar.cli.reconstruct",
    "lelsonar.cli.recordings",
    "lelsonar.cli.batch",
    "lelsonar.cli.bridge",
    "lelsonar.cli.demo",
    "lelsonar.tools.bench",
    "lelsonar.cli.warm_up",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lelsonar",
        description="Robust plane estimates from a rotating ultrasonic array (LEL fitting of L-shaped corners).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    from lelsonar.cli.config_file import add_config_arguments

    add_config_arguments(sub)  # every command reads --config; flags override it
    return parser


def main(argv: list[str] | None = None) -> int:
    from lelsonar.cli.config_file import parse_args
    from lelsonar.errors import LelsonarError

    try:
        args = parse_args(build_parser(), argv)
    except LelsonarError as exc:
        print(f"lelsonar: error: {exc}", file=sys.stderr)
        return 2
    import threading

    hook = threading.excepthook
    pipe_closed = _end_quietly_when_a_thread_loses_stdout()
    try:
        code = int(args.run(args) or 0)
        return 141 if pipe_closed.is_set() else code
    except LelsonarError as exc:
        print(f"lelsonar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return _stdout_closed()
    finally:
        threading.excepthook = hook


def _end_quietly_when_a_thread_loses_stdout():
    """A worker thread that prints (``planner --json``, live ``reconstruct --json``) and finds stdout closed
    stops the command as SIGTERM does (files finished, torque off), without a traceback.

    Returns the event that says it happened (the exit code is then 141).
    """
    import signal
    import threading

    closed = threading.Event()
    previous = threading.excepthook

    def hook(info) -> None:
        if info.exc_type is not None and issubclass(info.exc_type, BrokenPipeError):
            if not closed.is_set():
                closed.set()
                _stdout_closed()
                # To the main thread, where the command's own handler stops it cleanly.
                signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
            return
        previous(info)

    threading.excepthook = hook
    return closed


def _stdout_closed() -> int:
    """The reader of stdout went away (``lelsonar reconstruct --json | head``): exit quietly.

    Python would print a traceback, then another one when it flushes stdout at
    exit; pointing stdout at /dev/null stops the second.  128 + SIGPIPE, as a
    shell tool killed by the signal would report.
    """
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    finally:
        os.close(devnull)
    return 141
