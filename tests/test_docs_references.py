"""The project's texts point readers to sections by title: ``docs/calibration.md, "The box campaign"`` in a
config comment, ``(below, "Settings")`` inside a document, ``[calibration](calibration.md#what-the-bounds-allow)``
in Markdown. A section renamed or moved leaves such a pointer dangling with nothing to say so; these tests read
every pointer and check that the section it names exists in the file it names, and lies on the side of the
pointer that ``below`` or ``above`` says."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = {path.name: path for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]}
SOURCES = sorted(
    [ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md")]
    + [path for folder in ("conf", "campaigns") for path in (ROOT / folder).rglob("*.yaml")]
    + [path for folder in ("torchdem", "bo", "kpi", "scripts") for path in (ROOT / folder).rglob("*.py")])

QUOTED = r'"([^"\n]+(?:\n[ \t]*#?[ \t]*[^"\n]+)?)"'                  # a title, wrapped over at most two lines
IN_FILE = re.compile(r'(?:docs/)?([\w-]+\.md|README\b)\)?(?:[,:]\s*|\s+)(?:sections?\s+)?' + QUOTED + r'(?:\s+and\s+' + QUOTED + ')?')
SIDE_FIRST = re.compile(r'\b(below|above),\s+(?:sections?\s+)?' + QUOTED)
SIDE_LAST = re.compile(QUOTED + r'\s+\(?(below|above)\b')
SECTION = re.compile(r'\bsections?\s+' + QUOTED + r'(?:\s+and\s+' + QUOTED + ')?')
ANCHOR = re.compile(r'\]\(((?:docs/)?[\w-]+\.md)#([\w-]+)\)')
LEAD = re.compile(r'^(?:- )?\*\*(.+?)\*\*', re.M)


def _plain(title: str) -> str:
    """A title as compared: one space between words, comment marks of a wrapped line and end stops dropped."""
    return re.sub(r'\s*\n\s*#?\s*', ' ', title).strip().rstrip('.:').strip()


def _titles(text: str) -> list[tuple[int, str]]:
    """(offset, title) of every heading and every paragraph's bold lead (``**The fill's lower bound.**``)."""
    found = [(m.start(), m.group(1)) for m in re.finditer(r'^#+\s+(.+)$', text, re.M)]
    found += [(m.start(), m.group(1)) for m in LEAD.finditer(text)]
    return [(offset, _plain(title)) for offset, title in found]


def _where(title: str, text: str) -> list[int]:
    """Offsets of the sections a pointer's title names: the whole title, or its start up to a word's end."""
    title = _plain(title)
    return [offset for offset, candidate in _titles(text)
            if candidate == title or (candidate.startswith(title) and not candidate[len(title)].isalnum())]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')


def _pointers(path: Path):
    """(line, target document, title, side) of every pointer by title in ``path``; side is None, 'below' or 'above'."""
    text = path.read_text()
    taken = []
    for match in IN_FILE.finditer(text):
        document = 'README.md' if match.group(1) == 'README' else match.group(1)
        if document in DOCUMENTS:
            taken.append(match.span())
            for title in filter(None, match.group(2, 3)):
                yield text.count('\n', 0, match.start()) + 1, document, title, None, match.start()
    if path.suffix != '.md' or path.name not in DOCUMENTS:
        return
    for pattern, side_group, title_groups in ((SIDE_FIRST, 1, (2,)), (SIDE_LAST, 2, (1,)), (SECTION, None, (1, 2))):
        for match in pattern.finditer(text):
            if any(start <= match.start() < end for start, end in taken):
                continue
            taken.append(match.span())
            side = match.group(side_group) if side_group else None
            for title in filter(None, (match.group(g) for g in title_groups)):
                yield text.count('\n', 0, match.start()) + 1, path.name, title, side, match.start()


POINTERS = [(path, *pointer) for path in SOURCES for pointer in _pointers(path)]


def test_the_texts_point_to_sections_by_title():
    assert len(POINTERS) > 50                      # the patterns still read the texts' way of pointing


@pytest.mark.parametrize("path, line, document, title, side, offset", POINTERS,
                         ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, *_ in POINTERS])
def test_every_section_named_by_title_exists_where_the_pointer_says(path, line, document, title, side, offset):
    where = _where(title, DOCUMENTS[document].read_text())
    assert where, f'{path.relative_to(ROOT)}:{line} names "{_plain(title)}" in {document}, which has no such section'
    if side == 'below':
        assert any(found > offset for found in where), f'{path.relative_to(ROOT)}:{line}: "{_plain(title)}" lies above'
    if side == 'above':
        assert any(found < offset for found in where), f'{path.relative_to(ROOT)}:{line}: "{_plain(title)}" lies below'


ANCHORS = [(path, text.count('\n', 0, m.start()) + 1, m.group(1), m.group(2))
           for path in SOURCES if path.suffix == '.md' for text in (path.read_text(),) for m in ANCHOR.finditer(text)]


@pytest.mark.parametrize("path, line, target, anchor", ANCHORS,
                         ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, *_ in ANCHORS])
def test_every_link_to_a_heading_finds_it(path, line, target, anchor):
    document = (path.parent / target) if (path.parent / target).exists() else ROOT / target
    headings = re.findall(r'^#+\s+(.+)$', document.read_text(), re.M)
    assert anchor in {_slug(h) for h in headings}, f"{path.relative_to(ROOT)}:{line}: no heading of {target} has the anchor #{anchor}"


def test_a_renamed_section_is_caught(tmp_path):
    """The check fails on a pointer whose section is gone, and on one that says below for a section above it."""
    text = "# Guide\n\n## Settings\n\nSee below, \"Tuning\" and (above, \"Settings\").\n\n**Tuning the skin.** Text.\n"
    assert _where("Tuning", text) and _where("Settings", text)
    assert not _where("Tune", text)                    # a title's start must end on a word's end
    assert not _where("Speed", text)
    offset = text.index("below")
    assert all(found < offset for found in _where("Settings", text))
