"""The README a newcomer reads in five minutes, and the docs it links: short, current, every link alive."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"

#: Labels of past work that belong in git history, not in the documentation.
HISTORY = re.compile(r"\b(issue|session)s?\s+#?\d+", re.IGNORECASE)
#: Relative Markdown links: ``[text](target)`` whose target is not a URL or an anchor.
LINK = re.compile(r"\]\((?!https?://|mailto:|#)([^)\s]+)\)")


def _markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.glob("*.md"))]


def test_readme_is_at_most_250_lines() -> None:
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= 250, f"README.md has {n} lines; move detail into docs/*.md"


def test_readme_starts_with_the_two_commands() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    # The title, then the first code block: `make demo` and `make test`, before any prose.
    body = [line for line in lines[1:] if line.strip()]
    assert body and body[0].startswith("```"), "the README's first block after the title is the commands"
    end = next(i for i in range(1, len(body)) if body[i].startswith("```"))
    block = [line.split("#", 1)[0].strip() for line in body[1:end]]
    assert block[:2] == ["make demo", "make test"], block


def test_every_doc_is_linked_from_the_readme() -> None:
    text = README.read_text(encoding="utf-8")
    linked = {(ROOT / target.split("#", 1)[0]).resolve() for target in LINK.findall(text)}
    docs = {p.resolve() for p in DOCS.glob("*.md")}
    assert docs, "docs/ holds the detail the README links to"
    assert not docs - linked, f"not linked from README.md: {sorted(p.name for p in docs - linked)}"


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path: Path) -> None:
    missing = [
        target
        for target in LINK.findall(path.read_text(encoding="utf-8"))
        if not (path.parent / target.split("#", 1)[0]).exists()
    ]
    assert not missing, f"{path.name} links to files that do not exist: {missing}"


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_labels_of_past_work(path: Path) -> None:
    hits = [
        f"{n}: {line.strip()}"
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert not hits, f"{path.name} names issues or sessions (history lives in git): {hits}"


def test_no_issue_or_session_labels_in_the_package() -> None:
    """Comments say why, not which piece of work wrote them: the package, its schemas, tools and tests name no issue."""
    hits = [
        f"{path.relative_to(ROOT)}:{n}"
        for folder in ("schemas", "services", "tools", "tests")
        for path in sorted((ROOT / folder).rglob("*"))
        if path.suffix in {".py", ".proto", ".md", ".toml"} and not path.name.endswith("_pb2.py")
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert not hits, f"issue or session labels (history lives in git): {hits}"
