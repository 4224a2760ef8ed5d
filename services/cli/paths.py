"""The paths a command is given, checked before it starts: one line (exit 2) instead of a traceback mid-run.

One rule for every command that writes a file: an output path that exists is refused, unless
``--overwrite`` is given.  Nothing is replaced silently, the recording the README calls the source of
truth least of all.  An input must be a regular, readable file: a directory or a named pipe (which would
block the reader until a writer comes) is refused.
"""

from __future__ import annotations

import argparse
import os
import stat
from pathlib import Path

from lelsonar.errors import ConfigError, LelsonarError, RecordingNotFoundError

OVERWRITE_HELP = "replace output files that exist (without it, an existing output is refused)"


def add_overwrite_argument(p: argparse.ArgumentParser) -> None:
    """``--overwrite``, for every command that writes a file."""
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def input_file(path: Path | str, what: str = "recording", error: type[LelsonarError] = RecordingNotFoundError) -> Path:
    """``path`` if it is a regular file this process can read.

    Raises
    ------
    RecordingNotFoundError, or ``error``
        Missing, a directory, a named pipe or another special file, or unreadable.
    """
    p = Path(path)
    try:
        mode = p.stat().st_mode
    except FileNotFoundError:
        raise error(f"no {what} at {p}") from None
    except OSError as exc:
        raise error(f"cannot read {what} {p}: {exc.strerror}") from None
    if stat.S_ISDIR(mode):
        raise error(f"{p} is a directory; give a {what} in it")
    if not stat.S_ISREG(mode):
        raise error(f"{p} is not a regular file (a pipe or a device); give a {what} file")
    if not os.access(p, os.R_OK):
        raise error(f"cannot read {what} {p}: permission denied")
    return p


def output_file(path: Path | str, *, overwrite: bool, flag: str = "--overwrite", what: str = "output") -> Path:
    """``path`` checked as a file this command may create: its folder is made if need be.

    Raises
    ------
    ConfigError
        ``path`` exists (a file, without ``overwrite``; a directory or a special file, always), its
        folder is a file, or the folder is not writable.
    """
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{what} {p} is a directory; give a file name in it")
    if p.exists() or p.is_symlink():
        if not p.is_file():
            raise ConfigError(f"{what} {p} exists and is not a regular file; give another name")
        if not overwrite:
            raise ConfigError(f"{what} {p} exists; pass {flag} to replace it, or give another name")
    output_dir(p.parent, what=f"the folder of {what} {p}")
    return p


def output_dir(path: Path | str, *, what: str = "output folder") -> Path:
    """``path`` as a folder this command can write in, made if need be.

    Raises
    ------
    ConfigError
        A file is in the way, or the folder cannot be made or written.
    """
    d = Path(path)
    for parent in (d, *d.parents):
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(f"{what}: {parent} is a file, not a folder")
            break
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{what}: cannot make {d}: {exc.strerror}") from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise ConfigError(f"{what}: {d} is not writable")
    return d
