"""The documentation holds together: the README stays short, every relative link in README.md and
docs/**/*.md points at a file (and heading) that exists, and every docs page can be reached from
the README by following links, so nothing moved out of the README is lost."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path
from urllib.parse import unquote

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
README_MAX_LINES = 200

_FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.M | re.S)
_CODE_SPAN = re.compile(r"(`+).+?\1", re.S)
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$", re.M)


def doc_files() -> list[Path]:
    """README.md and every Markdown page under docs/, sorted."""
    return [README, *sorted((REPO / "docs").rglob("*.md"))]


def _prose(text: str) -> str:
    """The text with fenced blocks and code spans blanked: links in code are not links."""
    text = _FENCE.sub("", text)
    return _CODE_SPAN.sub("", text)


def links(path: Path) -> list[str]:
    """Every link target of a Markdown file outside code, in order of appearance."""
    return _LINK.findall(_prose(path.read_text(encoding="utf-8")))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: markup dropped, lower case, punctuation removed, spaces
    to hyphens."""
    text = re.sub(r"[`*]|<[^>]+>", "", heading).strip().lower()
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors GitHub gives a Markdown file's headings (repeats get -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for _, title in _HEADING.findall(_FENCE.sub("", path.read_text(encoding="utf-8"))):
        base = slug(title)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def _is_external(target: str) -> bool:
    return re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) is not None


def resolve(source: Path, target: str) -> tuple[Path, str]:
    """The file and anchor a relative link of ``source`` points at."""
    path, _, anchor = target.partition("#")
    return ((source.parent / unquote(path)).resolve() if path else source), anchor


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines, at most {README_MAX_LINES}"


def test_relative_links_point_at_files_and_headings_that_exist():
    broken = []
    checked = 0
    for source in doc_files():
        for target in links(source):
            if _is_external(target):
                continue
            checked += 1
            dest, anchor = resolve(source, target)
            rel = source.relative_to(REPO)
            if not dest.exists():
                broken.append(f"{rel}: {target} (no such file)")
            elif not dest.is_relative_to(REPO):
                broken.append(f"{rel}: {target} (outside the repository)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{rel}: {target} (no heading #{anchor} in {dest.name})")
    assert checked > 0, "no relative links found: the link pattern is broken"
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_docs_page_is_reachable_from_the_readme():
    reached = {README.resolve()}
    todo = [README]
    while todo:
        source = todo.pop()
        for target in links(source):
            if _is_external(target):
                continue
            dest, _ = resolve(source, target)
            if dest.suffix == ".md" and dest.exists() and dest not in reached:
                reached.add(dest)
                todo.append(dest)
    pages = {p.resolve() for p in doc_files()}
    missing = sorted(str(p.relative_to(REPO)) for p in pages - reached)
    assert not missing, "docs pages no link from README.md leads to: " + ", ".join(missing)


def test_readme_links_the_docs_index():
    targets = {resolve(README, t)[0] for t in links(README) if not _is_external(t)}
    assert (REPO / "docs" / "index.md").resolve() in targets


def test_slug_matches_github_anchors():
    assert slug("No walker waits: progressive PVS, and `auto` by measurement") == (
        "no-walker-waits-progressive-pvs-and-auto-by-measurement")
    assert slug("`from_segment` on the real scenes") == "from_segment-on-the-real-scenes"
    assert slug("Deploying: Docker and compose") == "deploying-docker-and-compose"


def test_link_finder_ignores_code_and_finds_images():
    sample = REPO / "docs" / "index.md"
    found = links(sample)
    assert found, "docs/index.md links no page"
    text = "see [a](x.md) and ![img](y.png) but not `[c](z.md)`\n```\n[d](w.md)\n```\n"
    assert _LINK.findall(_prose(text)) == ["x.md", "y.png"]
