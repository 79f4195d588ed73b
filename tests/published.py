"""The published tables under results/, for the tests that check each one's words against its numbers."""

from __future__ import annotations

from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results"


def published_tables() -> list[Path]:
    """The markdown of every table with run records under results/runs/ (its ``<table>.csv``)."""
    return sorted(RESULTS / f"{p.stem}.md" for p in (RESULTS / "runs").glob("*.csv") if p.name.count(".") == 1)
