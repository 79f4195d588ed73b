"""A table's numbers for papers and notebooks: ``<table>.csv`` (unformatted) and ``<table>.tex`` (booktabs) beside
its markdown, from the same summary and race the markdown shows.

The CSV has one line per row: its name, n, and per metric the mean, std and 95 % CI of the mean over seeds and the
paper's value; for the primary metric also the difference from the reference row with its 95 % CI and p-value
(:func:`ablate.tables.columns.row_difference`, paired over shared seeds, with the test frames' variance where the
runs kept counts per frame) and the race's verdict on that comparison
(``better``, ``worse``, ``equivalent``, ``different`` or ``undecided``, :mod:`ablate.tables.verdicts`; empty without
a race), and, where the race left it open, about how many seeds per row and CPU hours deciding it would take
(``decide_seeds``, ``decide_cpu_hours``: :mod:`ablate.tables.decide`; seeds -1 where no number of seeds would), and
where the race's seeds would not, the test frames that would at its last look (``decide_frames``), and the table's δ
(``rope``); on the top row, its verdict against the second (``top_vs_second``, as the footer says it) and what
deciding that would take (``top_decide_seeds``, ``top_decide_cpu_hours``, ``top_decide_frames``); and Kendall's τ between our ranking
and the paper's with the rows it compares (``kendall_tau``, ``kendall_n``). The results summary reads these. The LaTeX table shows mean ± std
per metric, the best of each column in bold (pandas' ``Styler``; names and labels escaped), with ``\\toprule``/``\\midrule``/``\\bottomrule``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.tables.columns import ahead_words, kind_of, replayed_race, row_difference, table_frames, top_and_second
from ablate.tables.cost import table_cost
from ablate.tables.decide import ToDecide, undecided
from ablate.tables.summary import bold_of, kendall, reference


def numbers(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """The table's numbers, unformatted: one line per row of ``summary`` (:func:`ablate.tables.summary.summarise`)."""
    key = str(table.primary)
    parts = {
        f"{metric}_{part}": summary[f"{metric}_{part}"].astype(float)
        for metric in table.metrics
        for part in ("mean", "std", "lo", "hi", "paper")
    }  # one frame, not a column at a time: DGFN's 58 metrics made pandas warn of a fragmented frame
    out = pd.concat([summary[["row", "name", "n"]], pd.DataFrame(parts, index=summary.index)], axis=1)
    raced = replayed_race(summary, runs, table, key) if len(summary) else None
    ref = (raced.reference if raced is not None else None) or reference(summary, table)
    deltas = []
    frames_var = table_frames(runs, table)
    todo = undecided(raced, runs) if raced is not None else {}
    none = decide_columns(None)
    for row in summary["row"]:
        if ref is None or row == ref or not len(runs):
            deltas.append({"delta": np.nan, "delta_lo": np.nan, "delta_hi": np.nan, "p": np.nan, "verdict": ""} | none)
            continue
        d = row_difference(runs, key, row, ref, raced, frames_var)
        verdict = "" if raced is None else kind_of(raced, row, ref)
        cost = decide_columns(todo.get(frozenset((row, ref))))
        deltas.append({"delta": d.delta, "delta_lo": d.ci.lo, "delta_hi": d.ci.hi, "p": d.p, "verdict": verdict} | cost)
    out["reference"] = ref or ""
    out = pd.concat([out.reset_index(drop=True), pd.DataFrame(deltas)], axis=1)
    found = top_and_second(summary, runs, key, raced, frames_var) if len(runs) else None
    rope = raced.plan.rope if raced is not None else None
    out["rope"] = np.nan if rope is None else rope
    out["top_vs_second"] = [
        ahead_words(found[2], found[3], rope) if found is not None and name == found[0] else "" for name in out["name"]
    ]
    top = decide_columns(todo.get(frozenset(raced.top)) if raced is not None and raced.top else None)
    for column, value in top.items():
        out[f"top_{column}"] = [value if found is not None and name == found[0] else np.nan for name in out["name"]]
    out["kendall_tau"], out["kendall_n"] = kendall(summary, key) if len(summary) else (np.nan, 0)
    spent = table_cost(raced, runs) if raced is not None else None  # the table's, on every line
    out["cpu_min"] = np.nan if spent is None else spent.total_min
    out["decided"] = np.nan if spent is None else spent.decided
    out["cpu_min_per_decision"] = np.nan if spent is None else spent.per_decision_min
    return out


def decide_columns(todo: ToDecide | None) -> dict[str, float]:
    """The CSV's columns on what deciding a comparison would take (:mod:`ablate.tables.decide`): seeds per row and
    CPU hours; NaN for a decided comparison, seeds -1 where no number of seeds would decide it; and the test frames
    that would at the race's last look's seeds, where its seeds would not (NaN where not estimated or none would)."""
    if todo is None:
        return {"decide_seeds": np.nan, "decide_cpu_hours": np.nan, "decide_frames": np.nan}
    frames = np.nan if todo.frames is None else todo.frames
    seeds = -1 if todo.seeds is None else todo.seeds
    return {"decide_seeds": seeds, "decide_cpu_hours": todo.cpu_hours, "decide_frames": frames}


def latex(summary: pd.DataFrame, table: DictConfig) -> str:
    """Mean ± std per metric, the best of each column in bold, as a booktabs LaTeX table."""
    shown = pd.DataFrame({"Row": summary["name"].astype(str)})
    best: dict[str, float] = {}
    for metric, label in table.metrics.items():
        mean, std = summary[f"{metric}_mean"].astype(float), summary[f"{metric}_std"].astype(float)
        shown[str(label)] = [
            "--" if np.isnan(m) else f"{m:.2f}" + ("" if np.isnan(s) else f" $\\pm$ {s:.2f}") for m, s in zip(mean, std)
        ]
        best[str(label)] = bold_of(mean, metric)
    means = {str(label): summary[f"{metric}_mean"].astype(float).tolist() for metric, label in table.metrics.items()}

    def bold(column: pd.Series) -> list[str]:
        if column.name not in means:
            return ["" for _ in column]
        return ["font-weight: bold" if m == best[str(column.name)] else "" for m in means[str(column.name)]]

    styler = shown.style.hide(axis="index").apply(bold, axis=0)
    styler = styler.format(escape="latex", subset=["Row"]).format_index(escape="latex", axis="columns")
    return styler.to_latex(hrules=True, convert_css=True, column_format="l" + "r" * len(table.metrics))


def write_numbers(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig, out: Path) -> list[Path]:
    """Write ``<table>.csv`` and ``<table>.tex`` under ``out``; the paths."""
    csv, tex = out / f"{table.name}.csv", out / f"{table.name}.tex"
    if summary.empty:  # no row has a finished run yet (a report while the first jobs train)
        pd.DataFrame(columns=["row", "name", "n"]).to_csv(csv, index=False, lineterminator="\n")
        tex.write_text("% no row has a finished run yet\n")
        return [csv, tex]
    numbers(summary, runs, table).to_csv(csv, index=False, lineterminator="\n")
    tex.write_text(latex(summary, table))
    return [csv, tex]
