"""Argument types for counts, seeds and durations: a value out of range is a usage error (one line, exit 2)
before the command starts, not a failure mid-run or a silent "run forever"."""

from __future__ import annotations

import argparse
import math


def count(text: str) -> int:
    """A whole number ≥ 0 (``--until-scans``, ``--seed``: 0 is a value of its own)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a whole number ≥ 0, got {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"takes a whole number ≥ 0, got {text!r}")
    return n


def positive_count(text: str) -> int:
    """A whole number ≥ 1 (how many runs, seeds, files)."""
    n = count(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"takes a whole number ≥ 1, got {text!r}")
    return n


def seconds(text: str) -> float:
    """A finite duration ≥ 0 s."""
    try:
        s = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a duration in seconds ≥ 0, got {text!r}") from None
    if not (math.isfinite(s) and s >= 0):
        raise argparse.ArgumentTypeError(f"takes a duration in seconds ≥ 0, got {text!r}")
    return s
