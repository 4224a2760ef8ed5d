"""The ``lelsonar`` command line: one console script, one subcommand per job.

Each subcommand is a module of this package (``lelsonar bench`` is the thin entry over
``tools/``) that exposes ``register(subparsers)``.  That function adds its parser and sets ``run`` to a
callable taking the parsed arguments and returning an exit code.  Configuration
objects are built here, from flags and TOML, never at import time.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys

#: Modules that contribute subcommands, in the order `--help` lists them.
COMMAND_MODULES = (
    "lelsonar.cli.contract",
    "lelsonar.cli.secure",
    "lelsonar.cli.acquire",
    "lelsonar.cli.simulate",
    "lelsonar.cli.emulate",
    "lelsonar.cli.reconstruct",
    "lelsonar.cli.review",
    "lelsonar.cli.planner",
    "lelsonar.cli.recordings",
    "lelsonar.cli.map",
    "lelsonar.cli.batch",
    "lelsonar.cli.bridge",
    "lelsonar.cli.demo",
    "lelsonar.tools.bench",
    "lelsonar.cli.warm_up",
)


#: The exit codes every command keeps (`lelsonar --help` shows them; the misuse test checks them).
EXIT_CODES = {
    0: "done",
    1: "the command ran and failed (no estimate, a device, network or disk failure)",
    2: "usage: a flag, value, path or configuration file is wrong (one line says which)",
    130: "interrupted by Ctrl-C (a service that runs until Ctrl-C exits 0)",
    141: "its reader closed stdout (`lelsonar info | head -1`), as a tool killed by SIGPIPE",
}

EPILOG = (
    "exit codes: "
    + "; ".join(f"{code} {text}" for code, text in EXIT_CODES.items())
    + ". Every error is one line on stderr. Files: no command replaces a file that exists; it refuses "
    "in one line unless given --overwrite. Set LELSONAR_TRACEBACK=1 to see the traceback of an "
    "unexpected error."
)


class OneLineParser(argparse.ArgumentParser):
    """A usage error is one line naming the command and where its help is, exit 2 (subcommands inherit it)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="lelsonar",
        description="Robust plane estimates from a rotating ultrasonic array (LEL fitting of L-shaped corners).",
        epilog=EPILOG,
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    from lelsonar.cli.config_file import add_config_arguments

    add_config_arguments(sub)  # every command reads --config; flags override it
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; every outcome is an exit code of :data:`EXIT_CODES` and at most one line on stderr."""
    command = "lelsonar"
    try:
        from lelsonar.cli.config_file import parse_args
        from lelsonar.errors import LelsonarError

        try:
            args = parse_args(build_parser(), argv)
        except LelsonarError as exc:
            return _fail(command, exc, 2)
        except SystemExit as exc:  # --help (0) or a usage error already printed (2)
            return exc.code if isinstance(exc.code, int) else 2
        command = f"lelsonar {args.command}"
        import threading

        hook = threading.excepthook
        handlers = _signal_handlers()
        pipe_closed = _end_quietly_when_a_thread_loses_stdout()
        try:
            code = int(args.run(args) or 0)
            return 141 if pipe_closed.is_set() else code
        finally:
            threading.excepthook = hook
            _restore(handlers)  # a command's Ctrl-C handler ends with it (main() may run again in-process)
    except KeyboardInterrupt:  # at start-up (imports) too
        print(f"{command}: interrupted", file=sys.stderr, flush=True)
        return 130
    except BrokenPipeError:
        return _stdout_closed()
    except Exception as exc:  # noqa: BLE001 - every error is one line and a documented exit code
        if os.environ.get("LELSONAR_TRACEBACK"):
            raise
        return _fail(command, exc, _exit_code(exc))


def _signal_handlers() -> dict:
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}


def _restore(handlers: dict) -> None:
    import signal

    for sig, handler in handlers.items():
        if handler is not None:
            signal.signal(sig, handler)


def _exit_code(exc: BaseException) -> int:
    """2 for what the user gave (a flag, a value, a path), 1 for a failure while running."""
    from lelsonar.errors import DeviceError, LelsonarError

    if isinstance(exc, LelsonarError):
        return 1 if isinstance(exc, DeviceError) else 2
    if isinstance(exc, OSError) and exc.errno in _PATH_ERRNOS and exc.filename is not None:
        return 2
    return 1


_PATH_ERRNOS = {errno.ENOENT, errno.EISDIR, errno.ENOTDIR, errno.EEXIST, errno.EACCES, errno.EPERM, errno.EROFS}


def _fail(command: str, exc: BaseException, code: int) -> int:
    from lelsonar.errors import LelsonarError

    if isinstance(exc, LelsonarError):
        text = str(exc)
    elif isinstance(exc, OSError) and exc.strerror:
        where = f" {exc.filename}" if exc.filename is not None else ""
        text = f"{exc.strerror}{where}".strip()
    else:
        text = f"{type(exc).__name__}: {exc} (unexpected; LELSONAR_TRACEBACK=1 shows where, please report it)"
    print(f"{command}: error: {' '.join(text.split())}", file=sys.stderr, flush=True)
    return code


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
                main_ident = threading.main_thread().ident
                if main_ident is not None:  # always set: the main thread is running
                    signal.pthread_kill(main_ident, signal.SIGTERM)
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
