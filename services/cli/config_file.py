"""``--config FILE.toml`` for every command: a table per command, ``[zenoh]`` for all; flags win.

A command's table holds its flags by their long names (``scan_timeout`` or
``scan-timeout``); ``[zenoh]`` holds ``mode``, ``connect``, ``listen``,
``zenoh_config`` and ``prefix`` for every command that takes them.  A flag given
on the command line overrides the file; a flag left at its default never does.
A command that reads its own tables from the file (``acquire``, ``calibrate``)
sets the parser default ``_own_config_table=True`` and gets only ``[zenoh]`` here.
The other tables of a rig file (``[array]``, ``[servo]``, ...) are
:mod:`lelsonar.acquire.rig`'s.
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path
from typing import Any

from lelsonar.errors import ConfigError

ZENOH_TABLE = "zenoh"
_UNSET = object()
_SKIP = {"help", "config", "run", "command"}


def add_config_arguments(subparsers: argparse._SubParsersAction) -> None:
    """Give every subcommand that has none a ``--config`` option."""
    for name, p in subparsers.choices.items():
        if any(a.dest == "config" for a in p._actions):
            continue
        p.add_argument(
            "--config",
            type=Path,
            metavar="FILE.toml",
            help=f"TOML file: its [{name}] table sets this command's flags by their long names, its "
            f"[zenoh] table the Zenoh flags; flags given here win (examples/rig.toml)",
        )


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _subparser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    sub = _subparsers(parser).get(command)
    if sub is None:
        raise ConfigError(f"no subcommand {command!r}")
    return sub


def _load(path: Path) -> dict[str, Any]:
    from lelsonar.cli.paths import input_file

    try:
        with open(input_file(path, "config file", error=ConfigError), "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is not valid TOML: not UTF-8 text") from None


def check_tables(path: Path, doc: dict[str, Any], commands: list[str]) -> None:
    """Every table of the file is a command's, ``[zenoh]`` or a rig table; a misspelt one is named with the fix.

    A table nobody reads would be ignored silently, and the flags it meant to set left at their defaults.
    """
    import difflib

    from lelsonar.acquire.rig import RIG_KEYS

    known = [*commands, ZENOH_TABLE, *RIG_KEYS]
    for table in doc:
        if table in known:
            continue
        close = difflib.get_close_matches(table, known, n=1, cutoff=0.6)
        hint = f"; did you mean [{close[0]}]?" if close else f"; known tables: {', '.join(known)}"
        kind = "table" if isinstance(doc[table], dict) else "top-level key"
        raise ConfigError(f"{path}: unknown {kind} [{table}]{hint}")


def _convert(action: argparse.Action, value: Any, where: str) -> Any:
    if isinstance(action, argparse._AppendAction):
        items = value if isinstance(value, list) else [value]
        return [_convert_one(action, v, where) for v in items]
    if action.nargs not in (None, "?") and isinstance(value, list):
        return [_convert_one(action, v, where) for v in value]
    return _convert_one(action, value, where)


def _convert_one(action: argparse.Action, value: Any, where: str) -> Any:
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if action.type is None and action.choices is None and not isinstance(value, str):
        # A string flag (e.g. --foxglove [HOST:]PORT) written as a TOML number means the number's text.
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        value = str(value)
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if callable(action.type) and action.type not in (int, float) and number:
        value = str(value)  # a range-checked type (lelsonar.cli.values) reads the number's text, as on the line
    if isinstance(value, str) and callable(action.type):
        try:
            value = action.type(value)
        except (TypeError, ValueError, argparse.ArgumentTypeError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
    elif action.type is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif action.type in (int, float) and not isinstance(value, action.type):
        raise ConfigError(f"{where} must be of type {action.type.__name__}, got {value!r}")
    elif callable(action.type) and action.type not in (int, float) and not isinstance(value, str):
        raise ConfigError(f"{where} must be a number or a string, got {value!r}")
    if action.choices is not None and value not in action.choices:
        raise ConfigError(f"{where} must be one of {', '.join(map(str, action.choices))}, got {value!r}")
    return value


def parse_args(
    parser: argparse.ArgumentParser, argv: list[str] | None, commands: list[str] | None = None
) -> argparse.Namespace:
    """Parse ``argv``; then fill every flag not given explicitly from ``--config``'s tables.

    ``commands``: every command a table may be named after (default: the parser's).
    """
    args = parser.parse_args(argv)
    path = getattr(args, "config", None)
    if path is None:
        return args
    sub = _subparser(parser, args.command)
    actions = {a.dest: a for a in sub._actions if a.dest not in _SKIP and not a.dest.startswith("_")}
    zenoh_dests = {"mode", "connect", "listen", "zenoh_config", "prefix"}
    doc = _load(Path(path))
    check_tables(Path(path), doc, commands if commands is not None else list(_subparsers(parser)))
    values: dict[str, tuple[Any, str]] = {}
    tables = [(ZENOH_TABLE, zenoh_dests & set(actions))]
    if not getattr(args, "_own_config_table", False):
        tables.append((args.command, set(actions) - zenoh_dests))
    for table, allowed in tables:
        given = doc.get(table, {})
        if not isinstance(given, dict):
            raise ConfigError(f"{path}: [{table}] must be a table")
        for key, value in given.items():
            dest = key.replace("-", "_")
            if table == ZENOH_TABLE and dest in zenoh_dests and dest not in allowed:
                continue  # a command without Zenoh ignores [zenoh]
            if dest not in allowed:
                known = ", ".join(sorted(allowed)) or "none"
                raise ConfigError(
                    f"{path}: unknown key {key!r} in [{table}] for `lelsonar {args.command}`; known: {known}"
                )
            values[dest] = (_convert(actions[dest], value, f"{path}: [{table}].{key}"), table)
    if not values:
        return args
    # Which flags did the command line give?  Parse again with sentinels as the defaults.
    saved = {dest: sub.get_default(dest) for dest in values}
    sub.set_defaults(
        **{dest: (None if isinstance(actions[dest], argparse._AppendAction) else _UNSET) for dest in values}
    )
    try:
        probe = parser.parse_args(argv)
    finally:
        sub.set_defaults(**saved)
    for dest, (value, _table) in values.items():
        given = getattr(probe, dest)
        if given is _UNSET or (given is None and isinstance(actions[dest], argparse._AppendAction)):
            setattr(args, dest, value)
    return args
