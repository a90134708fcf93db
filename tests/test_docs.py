"""The documentation's links: every relative link in the README and docs/ names a file that
exists, and every ``#anchor`` a heading of the page it points to (GitHub's rule for a
heading's anchor), so a renamed section or a moved table does not leave a dead link."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r" {0,3}(`{3,}|~{3,})")
HEADING = re.compile(r" {0,3}#{1,6}\s+(.*?)(?:\s+#+)?\s*$")
LINK = re.compile(r"\]\(<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\)")


def outside_code(page: Path) -> list[str]:
    """The lines of ``page`` outside fenced code blocks (``` or ~~~, closed by a fence of the
    same character at least as long)."""
    lines, fence = [], ""
    for line in page.read_text().splitlines():
        mark = FENCE.match(line)
        if fence:
            if mark and mark.group(1)[0] == fence[0] and len(mark.group(1)) >= len(fence):
                fence = ""
        elif mark:
            fence = mark.group(1)
        else:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text: a link reduced to its text, code marks dropped,
    lower case, punctuation dropped (letters, digits, ``_``, ``-`` and spaces kept), spaces
    turned into hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "")
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of ``page``'s headings; a taken anchor gets the first free ``-1``, ``-2``,
    ... as GitHub numbers repeats."""
    found: set[str] = set()
    for line in outside_code(page):
        if heading := HEADING.match(line):
            name, n = slug(heading.group(1)), 0
            while (f"{name}-{n}" if n else name) in found:
                n += 1
            found.add(f"{name}-{n}" if n else name)
    return found


def dead_links(page: Path) -> list[str]:
    """The relative links of ``page`` (outside code) whose file or anchor does not exist."""
    dead = []
    for line in outside_code(page):
        for target in LINK.findall(re.sub(r"(`+).*?\1", "", line)):
            if re.match(r"[a-z]+:", target):  # https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                dead.append(f"{target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                dead.append(f"{target} (no such heading)")
    return dead


def test_a_headings_anchor_is_githubs():
    assert slug("What the oracle's caution round a failed rover costs") == (
        "what-the-oracles-caution-round-a-failed-rover-costs"
    )
    assert slug("The off-policy family at 5 seeds (DDPG, 60,000 episodes)") == (
        "the-off-policy-family-at-5-seeds-ddpg-60000-episodes"
    )
    assert slug("`--network entity`: attention") == "--network-entity-attention"
    assert slug("Targets ([`targets.yaml`](targets.yaml))") == "targets-targetsyaml"


def test_a_dead_link_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# Top\n\n## Top ##\n\n# Top 1\n\n````\n```\n# not a heading\n```\n````\n")
    assert anchors(tmp_path / "a.md") == {"top", "top-1", "top-1-1"}
    page = tmp_path / "b.md"
    page.write_text(
        "[ok](a.md#top-1-1) [gone](a.md#not-a-heading) [none](c.md) [web](https://x.org/#y) [self](#b)\n"
        '[titled](c.md "t") `d[k](x)` and\n~~~\n[in code](c.md)\n~~~\n# B\n'
    )
    assert dead_links(page) == ["a.md#not-a-heading (no such heading)", "c.md (no such file)", "c.md (no such file)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_of_the_docs_leads_somewhere(page):
    assert not dead_links(page), dead_links(page)
