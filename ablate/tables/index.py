"""The results summary: one line per paper table, read from the tables' numbers under ``results/`` (``<table>.csv``,
:mod:`ablate.tables.export`) and their specs; a table published before it had numbers, from its markdown.

Per table: our top row and the paper's, Kendall's τ between the two rankings, whether the paper's headline holds
here, and a link. It is written between two markers (:data:`BEGIN`, :data:`END`) into ``results/README.md`` and
into the project's ``README.md`` where they hold them, by ``python -m ablate.report``; everything else in those
files is left as it is.

Readings:

- Our top row is the one the table's own footer names ("Top row X against the second, ...", the highest mean on
  the primary metric); the paper's top row is the best of the paper's numbers in the table's spec (the lowest for
  a cost) among the rows run here (a ``paper_only`` row, another system the paper quotes, is left out), under
  ``primary_condition`` for a conditions table.
- The paper's headline is read as "the paper's top row is the best row". Where our top row is the paper's, it
  *holds* where it is ahead of the second by more than the table's δ (or, in a table without one, beyond seed
  noise); it holds *by a lead of uncertain practical size* where it is ahead beyond seed noise but not surely by δ;
  it holds *within ±δ only* where the race finds the two equivalent; it is *not separable* where the race left them
  undecided (:mod:`ablate.tables.verdicts`). Otherwise it does *not hold*, and the line names our top row. Where
  the race left the top row against the second open, the line adds about how many seeds per row and CPU hours
  deciding it would take (:mod:`ablate.tables.decide`).
- A table without paper numbers (a follow-up) has no headline.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.tables.spec import LOWER_IS_BETTER

BEGIN, END = "<!-- results-summary:begin -->", "<!-- results-summary:end -->"
TOP = re.compile(
    r"Top row (?P<top>.+?) against the second, (?P<second>.+?), on (?P<label>.+?): (?P<verdict>.+?)\.(?=\s|$)"
)
TAU = re.compile(
    r"Kendall τ between our ranking and the paper's on .+?: (?P<tau>-?[0-9.]+)(?: over (?P<n>[0-9]+) rows)?"
)


@dataclass
class Summary:
    """One table's line of the results summary."""

    name: str
    title: str
    ours: str
    paper: str
    tau: str
    headline: str
    cost: str = "—"  # CPU hours per decided comparison, tuning and race together (ablate.tables.cost)


def paper_top(table: DictConfig) -> str | None:
    """The name of the row with the paper's best number on the primary metric, or None without paper numbers."""
    key = str(table.get("primary") or "")
    rows = {str(r["row"]): str(r.get("name", r["row"])) for r in table.get("rows") or []}
    values: dict[str, float] = {}
    if table.get("layout") == "conditions":
        for condition in table.get("conditions") or []:
            if condition["condition"] == table.get("primary_condition"):
                for row, metrics in (condition.get("paper") or {}).items():
                    if key in (metrics or {}):
                        values[str(row)] = float(metrics[key])
    else:
        for r in table.get("rows") or []:
            if r.get("paper_only"):  # another system of the paper, never run here: not the headline's row
                continue
            value = (r.get("paper") or {}).get(key)
            if value is not None:
                values[str(r["row"])] = float(value)
    if not values:
        return None
    pick = min if key in LOWER_IS_BETTER else max
    best = pick(values, key=lambda row: values[row])
    return rows.get(best, best)


def headline_of(verdict: str) -> str:
    """The paper's headline where our top row is the paper's, from the footer's words on it against the second
    (:func:`ablate.tables.columns.ahead_words`)."""
    verdict = re.sub(r"\s*\(the race's \w+\)$", "", verdict.rsplit(": ", 1)[-1].rstrip(" ."))  # the footer's words
    if verdict.startswith("ahead by more than δ") or verdict == "ahead beyond seed noise":
        return "holds"
    if verdict.startswith("ahead beyond seed noise"):
        return "holds, by a lead of uncertain practical size"
    if verdict.startswith("equivalent"):
        return "holds within ±δ only: equivalent to the second"
    return "not separable from seed noise"


#: A table's footer line on what its evidence cost (:meth:`ablate.tables.cost.Cost.words`).
COST = re.compile(
    r"Cost of the evidence: (?P<total>[0-9.]+) CPU min .*?(?:for (?P<decided>[0-9]+) of [0-9]+ comparison|and none of)"
)


def summarise_table(table: DictConfig, text: str) -> Summary:
    """The summary line of ``table`` (its spec) from ``text`` (its markdown)."""
    top = TOP.search(text)
    tau = TAU.search(text)
    paper = paper_top(table)
    ours = top["top"] if top else "—"
    if paper is None:
        headline = "—"
    elif top is None:
        headline = "undecided (too few seeds)"
    elif ours != paper:
        headline = "does not hold"
    else:
        headline = headline_of(top["verdict"])
    shown_tau = "—" if tau is None else f"{float(tau['tau']):.2f}" + (f" ({tau['n']} rows)" if tau["n"] else "")
    spent = COST.search(text)  # the footer's line (ablate.tables.cost), as its numbers give it
    cost = "—"
    if spent:
        total, decided = float(spent["total"]), int(spent["decided"] or 0)
        per = total / decided if decided else float("nan")
        cost = cost_of(pd.DataFrame({"cpu_min": [total], "decided": [decided], "cpu_min_per_decision": [per]}))
    return Summary(str(table.name), str(table.title), ours, paper or "—", shown_tau, headline, cost)


def summarise_numbers(table: DictConfig, numbers: pd.DataFrame) -> Summary:
    """The summary line of ``table`` (its spec) from its numbers (``<table>.csv``, :mod:`ablate.tables.export`)."""
    paper = paper_top(table)
    if numbers.empty or "top_vs_second" not in numbers:  # no row has a finished run yet
        return Summary(
            str(table.name),
            str(table.title),
            "—",
            paper or "—",
            "—",
            "—" if paper is None else "undecided (too few seeds)",
        )
    top = numbers[numbers["top_vs_second"].fillna("") != ""]
    ours = str(top["name"].iloc[0]) if len(top) else "—"
    verdict = str(top["top_vs_second"].iloc[0]) if len(top) else ""
    if paper is None:
        headline = "—"
    elif not len(top) or verdict.startswith("n/a"):
        headline = "undecided (too few seeds)"
    elif ours != paper:
        headline = "does not hold"
    else:
        headline = headline_of(verdict)
    if len(top) and "top_decide_seeds" in top and not np.isnan(seeds := float(top["top_decide_seeds"].iloc[0])):
        hours = float(top["top_decide_cpu_hours"].iloc[0])
        cost = "" if np.isnan(hours) else f", about {hours:.1f} CPU h"
        todo = (
            "no number of seeds would decide it" if seeds < 0 else f"deciding it: about {seeds:.0f} seeds per row{cost}"
        )
        frames = float(top["top_decide_frames"].iloc[0]) if "top_decide_frames" in top else np.nan
        todo += "" if np.isnan(frames) else f"; about {frames:.0f} test frames would at the race's last look"
        headline = f"top row vs second open; {todo}" if headline == "—" else f"{headline}; {todo}"
    tau, n = float(numbers["kendall_tau"].iloc[0]), int(numbers["kendall_n"].iloc[0])
    shown_tau = "—" if np.isnan(tau) else f"{tau:.2f} ({n} rows)"
    return Summary(str(table.name), str(table.title), ours, paper or "—", shown_tau, headline, cost_of(numbers))


def cost_of(numbers: pd.DataFrame) -> str:
    """The summary's cost cell: CPU hours per decided comparison, or the hours spent where none was decided; "—"
    for numbers written before the cost was (:mod:`ablate.tables.cost`)."""
    if "cpu_min" not in numbers or np.isnan(total := float(numbers["cpu_min"].iloc[0])):
        return "—"
    decided = int(numbers["decided"].iloc[0])
    if not decided:
        return f"none decided ({total / 60:.1f} CPU h)"
    return f"{float(numbers['cpu_min_per_decision'].iloc[0]) / 60:.1f} ({decided} decided, {total / 60:.1f} CPU h)"


def markdown(summaries: list[Summary], link_prefix: str = "") -> str:
    """The summary as a markdown table, between the markers."""
    lines = [
        BEGIN,
        "| Table | Our top row | Paper's top row | Kendall τ | Paper's headline here | CPU h per decided comparison |",
        "|:--|:--|:--|:--|:--|:--|",
    ]
    for s in summaries:
        lines.append(
            f"| [{s.name}]({link_prefix}{s.name}.md) | {s.ours} | {s.paper} | {s.tau} | {s.headline} | {s.cost} |"
        )
    lines += [
        "",
        "Headline: the paper's top row is the best row, ahead of the second by more than the table's δ (beyond "
        "seed noise in a table raced without a δ; `ablate.tables.index`, `ablate.tables.verdicts`). CPU h per "
        "decided comparison: the tuning phase's and the race's CPU time over the comparisons the race decided, on the "
        "machine that made the runs (`ablate.tables.cost`). Regenerated by `python -m ablate.report`.",
        END,
    ]
    return "\n".join(lines)


def splice(path: Path, block: str) -> bool:
    """Replace the text between the markers in ``path`` with ``block``; False where the file or markers are
    missing (the file is then left alone)."""
    if not path.is_file():
        return False
    text = path.read_text()
    if BEGIN not in text or END not in text:
        return False
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    path.write_text(head + block + tail)
    return True


def write_index(tables: list[DictConfig], results_dir: str | Path, readme: str | Path | None = None) -> list[Path]:
    """Write the summary of every table of ``tables`` (their specs) that has a markdown file under ``results_dir``
    into ``results_dir/README.md`` and into ``readme`` (links there point into ``results_dir``); return the files
    written."""
    out = Path(results_dir)
    summaries = [
        summarise_numbers(t, pd.read_csv(out / f"{t.name}.csv"))
        if (out / f"{t.name}.csv").is_file()
        else summarise_table(t, (out / f"{t.name}.md").read_text())  # a table published before its numbers were
        for t in tables
        if (out / f"{t.name}.md").is_file()
    ]
    written = []
    if splice(out / "README.md", markdown(summaries)):
        written.append(out / "README.md")
    if readme is not None:
        prefix = f"{Path(out).as_posix().rstrip('/')}/"
        if splice(Path(readme), markdown(summaries, prefix)):
            written.append(Path(readme))
    return written
