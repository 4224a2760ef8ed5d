"""A bench's table as Markdown (``--markdown OUT.md``): the same rows the console shows, for a report or a PR."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

_MARKUP = re.compile(r"\[/?[a-z ]*\]")  # rich's [bold], [red], [/] …


def plain(text: object) -> str:
    """A cell without rich markup, with its pipes escaped."""
    return _MARKUP.sub("", str(text)).replace("|", "\\|").replace("\n", " ")


def table(title: str, headers: Sequence[str], rows: Sequence[Sequence[object]], notes: Sequence[str] = ()) -> str:
    """One Markdown table: a title line, the table, then each note as a line below it."""
    out = [f"### {plain(title)}", "", "| " + " | ".join(plain(h) for h in headers) + " |"]
    out.append("|" + "|".join("---" for _ in headers) + "|")
    out += ["| " + " | ".join(plain(c) for c in row) + " |" for row in rows]
    if notes:
        out.append("")
        out += [f"- {plain(n)}" for n in notes]
    return "\n".join(out) + "\n"


def write(path: Path | None, sections: Sequence[str]) -> None:
    """Write the sections to ``path`` (nothing when None), one blank line apart."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(sections), encoding="utf-8")
