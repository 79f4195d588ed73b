"""A table's verdicts at a glance: ``<table>_verdicts.png``, a forest plot of every comparison of its race (each row
against the reference, the top row against the second) on the primary metric: the mean paired difference over the
seeds with the interval its verdict read (the (1 - 2 level) interval of TOST at the look where the comparison ended,
:mod:`ablate.tables.verdicts`), against the ±δ band of the table's region of practical equivalence. An interval
inside the band is *equivalent*, one wholly beyond it *better* or *worse*, one that crosses it *of uncertain
practical size*. Made from the same race the table's footer reports (:func:`ablate.tables.racing.race`, replayed from
the runs), so the two never disagree."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from ablate.tables.columns import replay  # noqa: E402
from ablate.tables.comparison import Comparison  # noqa: E402
from ablate.tables.racing import RaceState, table_values  # noqa: E402
from ablate.tables.spec import row_names  # noqa: E402
from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, UNDECIDED, WORSE  # noqa: E402

COLOURS = {BETTER: "tab:green", WORSE: "tab:red", EQUIVALENT: "tab:blue", DIFFERENT: "tab:orange", UNDECIDED: "grey"}


def table_race(table: DictConfig, runs: pd.DataFrame) -> RaceState | None:
    """The race of ``table``'s runs replayed, with the table's δ; None without a race plan or runs."""
    if not len(runs):
        return None
    values = table_values(runs, table)
    return replay(runs, table, [str(r.row) for r in table.rows if str(r.row) in values], values, str(table.primary))


def plot(state: RaceState, table: DictConfig) -> Figure:
    """The forest plot of ``state``'s comparisons (see the module)."""
    names = row_names(table)
    comparisons: list[Comparison] = list(state.comparisons.values())
    label = table.metrics.get(table.primary, table.primary)
    fig, ax = plt.subplots(figsize=(7.0, 0.55 * len(comparisons) + 1.6))
    rope = state.plan.rope
    if rope is not None:
        ax.axvspan(-rope, rope, color="tab:blue", alpha=0.12, label=f"±δ = {rope:g} (practical equivalence)")
    ax.axvline(0.0, color="black", linewidth=0.8)
    for y, c in enumerate(reversed(comparisons)):
        colour = COLOURS[c.kind]
        if not math.isnan(c.lo):
            ax.plot([c.lo, c.hi], [y, y], color=colour, linewidth=2.5)
        ax.plot([c.delta], [y], "o", color=colour)
        ax.annotate(c.short(), (c.delta, y), xytext=(0, 6), textcoords="offset points", fontsize=7,
                    ha="center", color=colour)  # fmt: skip
    ax.set_yticks(
        range(len(comparisons)),
        [f"{names.get(c.a, c.a)} − {names.get(c.b, c.b)}" for c in reversed(comparisons)],
        fontsize=8,
    )
    ax.set_ylim(-0.7, len(comparisons) - 0.3)
    ax.margins(x=0.15)  # room for the words beside the outermost points
    ax.set_xlabel(f"Δ {label}\n(mean over paired seeds; bar: the interval the verdict read)", fontsize=9)
    ax.set_title(textwrap.fill(f"{table.title}: the race's verdicts", 70), fontsize=9)
    if rope is not None:
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def write_forest(table: DictConfig, runs: pd.DataFrame, results_dir: str | Path) -> Path | None:
    """``<table>_verdicts.png`` under ``results_dir``; None where the table has no race or no comparison."""
    state = table_race(table, runs)
    if state is None or not state.comparisons:
        return None
    path = Path(results_dir) / f"{table.name}_verdicts.png"
    fig = plot(state, table)
    fig.savefig(path, dpi=100, metadata={"Software": None}, bbox_inches="tight", pad_inches=0.1)  # long row names
    plt.close(fig)
    return path
