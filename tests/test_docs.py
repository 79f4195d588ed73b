"""The documentation keeps its size and its links. A newcomer reads the README (at most 1,200 words), the pages under
docs/ (8,000 in all) and results/README.md (2,000), counted as ``wc -w`` counts them. Every ``docs/<page>.md#anchor``
that the code, the configs, the benchmarks and the pages name is a heading of that page by GitHub's anchor rule, and
every relative link of a page points to a file that exists (and, with an anchor, to a heading of it): a heading
renamed or a page moved fails here, not in a reader's browser."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Where a page's words are counted, and the most each may hold.
BUDGETS = [("README.md", 1200), ("docs/*.md", 8000), ("results/README.md", 2000)]
#: The files that name documentation pages, as ``docs/<page>.md`` or ``docs/<page>.md#anchor``.
NAMING = [
    "README.md",
    "docs/*.md",
    "results/*.md",
    "ablate/**/*.py",
    "conf/**/*.yaml",
    "hydra_plugins/**/*.py",
    "scripts/*.py",
    "bench/*.py",
]
#: The pages whose markdown links are followed.
PAGES = ["README.md", "docs/*.md", "results/*.md"]

NAMED = re.compile(r"docs/([a-z_]+\.md)(?:#([\w-]+))?")
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"#{1,6}\s+(.+?)\s*#*\s*$")


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (``-`` and ``_`` kept), spaces to ``-``."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of a markdown page's headings, fenced code left out; a repeated heading's gets ``-1``, ``-2``."""
    seen: dict[str, int] = {}
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            continue
        heading = None if fenced else HEADING.match(line)
        if heading:
            name = slug(heading.group(1))
            seen[name] = seen.get(name, -1) + 1
            if seen[name]:
                seen[f"{name}-{seen[name]}"] = 0
    return set(seen)


def files(root: Path, patterns: list[str]) -> list[Path]:
    """The files under ``root`` that the glob patterns match, each once."""
    return sorted({p for pattern in patterns for p in root.glob(pattern) if p.is_file()})


def broken(root: Path) -> list[str]:
    """Every named page or anchor, and every relative link, under ``root`` that does not resolve, as
    ``file: target (why)``."""
    found: list[str] = []
    for source in files(root, NAMING):
        for page, anchor in NAMED.findall(source.read_text(encoding="utf-8")):
            target = root / "docs" / page
            if not target.is_file():
                found.append(f"{source.relative_to(root)}: docs/{page} (no such page)")
            elif anchor and anchor not in anchors(target):
                found.append(f"{source.relative_to(root)}: docs/{page}#{anchor} (no such heading)")
    for source in files(root, PAGES):
        for link in LINK.findall(source.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", link):  # https:, mailto:
                continue
            path, _, anchor = link.partition("#")
            target = (source.parent / path) if path else source
            if not target.exists():
                found.append(f"{source.relative_to(root)}: {link} (no such file)")
            elif anchor and target.suffix == ".md" and anchor not in anchors(target):
                found.append(f"{source.relative_to(root)}: {link} (no such heading)")
    return found


@pytest.mark.parametrize(("pattern", "budget"), BUDGETS)
def test_each_part_of_the_documentation_keeps_its_word_budget(pattern: str, budget: int) -> None:
    pages = files(REPO, [pattern])
    assert pages, pattern
    words = sum(len(p.read_text(encoding="utf-8").split()) for p in pages)
    assert words <= budget, f"{pattern}: {words} words, over its budget of {budget}"


def test_every_documentation_link_resolves() -> None:
    named = [m for source in files(REPO, NAMING) for m in NAMED.findall(source.read_text(encoding="utf-8"))]
    assert len([anchor for _, anchor in named if anchor]) >= 40  # the configs' and the tables' links were read
    assert broken(REPO) == []


def test_anchors_follow_githubs_rule() -> None:
    assert slug("Task: detection") == "task-detection"
    assert slug("The machine's numerics as a source of variance") == "the-machines-numerics-as-a-source-of-variance"
    assert slug("δ: one rule for every table") == "δ-one-rule-for-every-table"
    assert slug("detection_cpu") == "detection_cpu"
    assert slug("Batch normalisation (`recipe.batch_norm`, not in DGFN)") == (
        "batch-normalisation-recipebatch_norm-not-in-dgfn"
    )


def test_a_renamed_heading_a_missing_page_and_a_dead_link_are_each_reported(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "conf").mkdir()
    (tmp_path / "docs" / "guide.md").write_text(
        "# Guide\n\n## Scale out\n\n```bash\n# not a heading\n```\n\n## Scale out\n\n[ok](guide.md#scale-out-1) "
        "[gone](missing.md) [stale](guide.md#not-a-heading) [web](https://example.org/x.md)\n"
    )
    (tmp_path / "conf" / "a.yaml").write_text(
        "x: 1  # docs/guide.md#scale-out\ny: 2  # docs/guide.md#scaling-out\nz: 3  # docs/howto.md\n"
    )
    assert broken(tmp_path) == [
        "conf/a.yaml: docs/guide.md#scaling-out (no such heading)",
        "conf/a.yaml: docs/howto.md (no such page)",
        "docs/guide.md: missing.md (no such file)",
        "docs/guide.md: guide.md#not-a-heading (no such heading)",
    ]
