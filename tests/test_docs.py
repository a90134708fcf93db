"""The documentation's links: every relative link in the README and docs/ names a file that
exists, and every ``#anchor`` a heading of the page it points to (GitHub's rule for a
heading's anchor), so a renamed section or a moved table does not leave a dead link."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (letters, digits, ``_``,
    ``-`` and spaces kept), spaces turned into hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of ``page``'s headings outside code blocks; a repeated heading's n-th
    repeat gets ``-n``, as GitHub numbers them."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    fenced = False
    for line in page.read_text().splitlines():
        fenced ^= line.startswith("```")
        heading = re.match(r"#+\s+(.*)", line)
        if heading and not fenced:
            name = slug(heading.group(1))
            found.add(f"{name}-{seen[name]}" if name in seen else name)
            seen[name] = seen.get(name, 0) + 1
    return found


def dead_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file or anchor does not exist."""
    dead = []
    for target in LINK.findall(page.read_text()):
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


def test_a_dead_link_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# Top\n\n## Top\n\n```\n# not a heading\n```\n")
    page = tmp_path / "b.md"
    page.write_text(
        "[ok](a.md#top-1) [gone](a.md#not-a-heading) [none](c.md) [web](https://x.org/#y) [self](#b)\n\n# B\n"
    )
    assert dead_links(page) == ["a.md#not-a-heading (no such heading)", "c.md (no such file)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_of_the_docs_leads_somewhere(page):
    assert not dead_links(page), dead_links(page)
