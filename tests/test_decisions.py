"""The decisions (docs/decisions/): split by subject from one page of 96 sections, none lost,
each listed in the index, and every citation of a decision names a page and a text it holds.

The single page's ``## `` headings as they stood when it was split (session 38, b4843d6) are
``tests/data/decisions_sections.txt``, one a line."""

import os
import re
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DECISIONS = ROOT / "docs" / "decisions"
INDEX = DECISIONS / "index.md"
OLD_SECTIONS = (Path(__file__).parent / "data" / "decisions_sections.txt").read_text().splitlines()
TEXT_SUFFIXES = {".py", ".md", ".toml", ".yml", ".yaml", ".txt", ".cfg", ".html", ".js", ".sh", ".ini"}


def pages() -> dict[str, str]:
    return {p.stem: p.read_text() for p in sorted(DECISIONS.glob("*.md")) if p.name != "index.md"}


def headings(text: str, level: int = 2) -> list[str]:
    """The ``level`` headings of a Markdown text, outside fenced code."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#" * level + " "):
            out.append(line[level + 1:].strip())
    return out


def lost_or_doubled(by_page: dict[str, list[str]], old: list[str]) -> list[str]:
    """What is wrong with the pages' sections against the single page's: a section missing or on
    the pages more than once, or two sections of one page out of their recorded order."""
    count = Counter(t for secs in by_page.values() for t in secs)
    wrong = [f"missing: {t}" for t in old if count[t] == 0]
    wrong += [f"{count[t]} times: {t}" for t in old if count[t] > 1]
    rank = {t: i for i, t in enumerate(old)}
    for page, secs in by_page.items():
        kept = [rank[t] for t in secs if t in rank]
        if kept != sorted(kept):
            wrong.append(f"{page}.md: sections out of their recorded order")
    return wrong


def test_the_split_kept_every_section_once_in_its_order():
    assert len(OLD_SECTIONS) == 96 and len(set(OLD_SECTIONS)) == 96
    by_page = {name: headings(text) for name, text in pages().items()}
    assert len(by_page) >= 8
    assert lost_or_doubled(by_page, OLD_SECTIONS) == []


def test_a_dropped_or_doubled_section_is_found():
    by_page = {name: headings(text) for name, text in pages().items()}
    first = next(iter(by_page))
    dropped = {**by_page, first: by_page[first][1:]}
    assert lost_or_doubled(dropped, OLD_SECTIONS) == [f"missing: {by_page[first][0]}"]
    doubled = {**by_page, "extra": [OLD_SECTIONS[5]]}
    assert lost_or_doubled(doubled, OLD_SECTIONS) == [f"2 times: {OLD_SECTIONS[5]}"]
    swapped = {**by_page, first: by_page[first][1::-1] + by_page[first][2:]}
    assert lost_or_doubled(swapped, OLD_SECTIONS) == [f"{first}.md: sections out of their recorded order"]


def test_the_index_lists_every_page_and_section_in_order():
    """A new section is appended to its page and listed here (the house rule the index states);
    the anchors themselves are checked by ``mkdocs build --strict`` (tests/test_docs.py)."""
    index = INDEX.read_text()
    assert "## Where a new decision goes" in index
    for name, text in pages().items():
        assert f"]({name}.md)" in index, f"docs/decisions/index.md does not link {name}.md"
        listed = re.findall(rf"^- \[(.+)\]\({re.escape(name)}\.md#[^)]+\)$", index, flags=re.M)
        assert listed == headings(text), f"docs/decisions/index.md's list for {name}.md differs from its sections"


def _text_files():
    skip = {".git", ".ci", "site", "node_modules", "__pycache__", ".mypy_cache", ".pytest_cache", ".ruff_cache"}
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in skip and not d.endswith(".egg-info")]
        for name in files:
            path = Path(folder) / name
            if path.suffix in TEXT_SUFFIXES and DECISIONS not in path.parents and path != Path(__file__):
                yield path


def _flat(text: str) -> str:
    """Lines joined as one, comment markers of a continued comment dropped, spaces collapsed."""
    return re.sub(r"\s+", " ", re.sub(r"\n\s*(?:#|//|\*)?\s*", " ", text)).lower()


CITATION = re.compile(r"docs/decisions(\.md|/(?:[\w-]+\.md)?)")
QUOTED = re.compile(r"""^`?(?:,\s*|\s+\(?)\\?["“]([^"”\\]+)""")  # , "…" or ("…") or "…" after the page


def test_every_citation_names_a_page_and_what_it_holds():
    """Code, docs and reports cite ``docs/decisions/<page>.md, "<title or phrase>"``: the page
    exists and holds the quoted words (so a reader finds them), and nothing cites the single
    page that was split."""
    flat_pages = {name: _flat(text) for name, text in pages().items()}
    wrong, cited = [], 0
    for path in _text_files():
        text = path.read_text(errors="replace")
        for m in CITATION.finditer(text):
            where = f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}"
            target = m.group(1)
            if target == ".md":
                wrong.append(f"{where}: cites docs/decisions.md (split into docs/decisions/)")
                continue
            name = target.strip("/").removesuffix(".md")
            if name in ("", "index"):
                continue
            if name not in flat_pages:
                wrong.append(f"{where}: no page docs/decisions/{name}.md")
                continue
            cited += 1
            quote = QUOTED.match(_flat(text[m.end():m.end() + 300]))
            if quote:
                words = quote.group(1).strip(" …").rstrip(".")
                if words not in flat_pages[name]:
                    wrong.append(f'{where}: docs/decisions/{name}.md does not hold "{words}"')
    assert cited > 100
    assert wrong == []
