"""The docs are reference pages: a short README, no dated headings (CHANGELOG.md holds the
dates), no links out of the repository, no broken links inside it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").rglob("*.md"))  # docs/report.md (generated) included
PAGES = [ROOT / "README.md", *DOCS]
MONTHS = ("January|February|March|April|May|June|July|August|September|October|November|"
          "December|Jan|Feb|Mar|Apr|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec")
DATE = re.compile(rf"\b\d{{4}}-\d{{2}}-\d{{2}}\b|\b(?:{MONTHS})\.?\s+(?:\d{{1,2}},?\s+)?\d{{4}}\b",
                  re.I)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _headings(text: str) -> list[str]:
    """Markdown ATX headings outside fenced code blocks."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return [ln for ln in prose.splitlines() if re.match(r"#{1,6}\s", ln)]


def _links(text: str) -> list[str]:
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    prose = re.sub(r"`[^`\n]*`", "", prose)
    return LINK.findall(prose) + re.findall(r"<(https?://[^>]+)>", prose)


def test_readme_is_at_most_250_lines():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 250, f"README.md has {n} lines"


def test_the_pages_were_found():
    names = {p.relative_to(ROOT).as_posix() for p in PAGES}
    assert {"README.md", "docs/TRAINING.md", "docs/BENCHMARKS.md", "docs/MODEL.md",
            "docs/report.md"} <= names, names


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_heading_under_docs_carries_a_date(page):
    dated = [h for h in _headings(page.read_text()) if DATE.search(h)]
    assert not dated, f"{page.relative_to(ROOT)}: dated headings {dated} (dates go in CHANGELOG.md)"


def test_the_date_pattern_finds_dates_and_only_dates():
    for h in ("## Runs (2026-12-07)", "### Made in December 2026", "## Nov 22, 2026 figures",
              "## sept. 2025"):
        assert DATE.search(h), h
    for h in ("## 1. The site model", "### 3.6 The rollout planner", "## `N_V` 5: 2026 trips",
              "## Phase 3: K = 16, H = 200", "## The 1000 x 10 000 protocol"):
        assert not DATE.search(h), h


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_page_links_outside_the_repository(page):
    outside = [u for u in _links(page.read_text()) if re.match(r"[a-z][a-z0-9+.-]*:", u, re.I)]
    assert not outside, f"{page.relative_to(ROOT)} links outside the repository: {outside}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_to_files_that_exist(page):
    broken = []
    for url in _links(page.read_text()):
        path = url.split("#", 1)[0]
        if not path or re.match(r"[a-z][a-z0-9+.-]*:", path, re.I):
            continue
        target = (page.parent / path).resolve()
        if not target.exists():
            broken.append(url)
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files {broken}"


def test_the_link_checks_read_links():
    text = "See [a](docs/MODEL.md), ![fig](figures/x.png) and <https://example.org>.\n" \
           "```\n[not](a-link.md)\n```\n`[nor](this.md)`"
    assert _links(text) == ["docs/MODEL.md", "figures/x.png", "https://example.org"]
    assert "docs/ARCHITECTURE.md" in _links((ROOT / "README.md").read_text())
