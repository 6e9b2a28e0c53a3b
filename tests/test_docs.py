"""The documents' links hold: every `FILE.md#anchor` that the package, the tests, the grids and
the documents point to names a heading of that file, and BENCHMARKS.md stays a page of today's
results (at most 400 lines, with the headings other files name in prose). Plain text checks,
no Ray."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = {  # how files refer to a document -> the document
    "BENCHMARKS.md": ROOT / "BENCHMARKS.md",
    "model.md": ROOT / "docs" / "model.md",
    "cluster.md": ROOT / "docs" / "cluster.md",
    "benchmarks-2026.md": ROOT / "docs" / "history" / "benchmarks-2026.md",
}
LINK = re.compile(r"\b(BENCHMARKS\.md|model\.md|cluster\.md|benchmarks-2026\.md)#([A-Za-z0-9_-]+)")
IN_PAGE = re.compile(r"\]\(#([A-Za-z0-9_-]+)\)")
SOURCES = [
    *(ROOT / "uavlora_rllib").rglob("*.py"),
    *(ROOT / "tests").rglob("*.py"),
    *(ROOT / "analysis").rglob("*.py"),
    *(ROOT / "tune_configs").glob("*.yaml"),
    *(ROOT / "docs").rglob("*.md"),
    ROOT / "README.md",
    ROOT / "BENCHMARKS.md",
]


def slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6} +(.+?) *$", text, re.M)}


def test_slug_matches_githubs_rule():
    assert slug("Open-loop check and per_device references (issue 23)") == (
        "open-loop-check-and-per_device-references-issue-23"
    )
    assert slug("Baselines (execution phase, paper scenario V=10, U=2, T=150)") == (
        "baselines-execution-phase-paper-scenario-v10-u2-t150"
    )


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_anchor_names_a_heading(path):
    text = path.read_text()
    broken = [f"{name}#{anchor}" for name, anchor in LINK.findall(text) if anchor not in anchors(DOCS[name])]
    if path.suffix == ".md":  # links within the page
        broken += [f"#{a}" for a in IN_PAGE.findall(text) if a not in anchors(path)]
    assert not broken, f"{path.relative_to(ROOT)}: no such heading: {broken}"


def test_benchmarks_holds_todays_results_only():
    text = (ROOT / "BENCHMARKS.md").read_text()
    assert len(text.splitlines()) <= 400
    headings = re.findall(r"^## (.+)$", text, re.M)
    assert "Simulator" in headings  # `python -m uavlora_rllib.bench env --write` replaces it
    for named in ("Open-loop check and per_device references", "Learning at scale", "Model checks"):
        assert any(h.startswith(named) for h in headings), named  # named in prose elsewhere
    assert "chronological log" in (ROOT / "docs" / "history" / "benchmarks-2026.md").read_text()[:600]


def test_relative_links_of_every_document_exist():
    """Every relative markdown link (or image) of README.md, BENCHMARKS.md and docs/ names a file or folder, resolved
    from the page's own folder (a paragraph moved into docs/history/ keeps no root-relative link)."""
    broken = []
    for page in (ROOT / "README.md", ROOT / "BENCHMARKS.md", *(ROOT / "docs").rglob("*.md")):
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        targets = [*re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text), *re.findall(r'<img src="([^":]+)"', text)]
        broken += [f"{page.relative_to(ROOT)}: {t}" for t in targets if not (page.parent / t).exists()]
    assert not broken, broken


def test_nothing_imports_the_raw_measurements():
    for path in [*(ROOT / "uavlora_rllib").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]:
        assert not re.search(r"^\s*(from|import)\s+\S*measurements", path.read_text(), re.M), path
