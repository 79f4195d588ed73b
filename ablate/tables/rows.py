"""The ``rows`` layout: a row per trained model, ``results/<table>.md`` and ``results/<table>.png``.

A row with ``paper_only: true`` is another system of the paper, listed with the paper's numbers and never run;
``table.text_columns`` ({key: label}) adds text columns read from each row. A table with ``primary_condition``
shows its metrics under that test condition (``<condition>/<metric>``).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from ablate.store import Tracker  # noqa: E402
from ablate.tables.collect import under_condition  # noqa: E402
from ablate.tables.columns import costs, significance  # noqa: E402
from ablate.tables.export import write_numbers  # noqa: E402
from ablate.tables.provenance import provenance  # noqa: E402
from ablate.tables.spec import COSTS  # noqa: E402
from ablate.tables.summary import bold_of, fmt, kendall, summarise  # noqa: E402


def metric_columns(summary: pd.DataFrame, table: DictConfig, keys: list[str]) -> dict[str, list[str]]:
    """Ours (mean ± std, the column's best bold) and, where the paper gives any, the paper's, for each of ``keys``."""
    columns: dict[str, list[str]] = {}
    for key in keys:
        label = table.metrics[key]
        best = bold_of(summary[f"{key}_mean"], key)
        columns[f"{label} (ours)"] = [
            fmt(m, s, m == best) for m, s in zip(summary[f"{key}_mean"], summary[f"{key}_std"])
        ]
        paper = summary[f"{key}_paper"]
        if paper.notna().any():
            pbest = bold_of(paper, key)
            columns[f"{label} (paper)"] = [fmt(p, np.nan, p == pbest) for p in paper]
    return columns


#: The cost columns of the main table; the latency itself (median [IQR], ours and the paper's) is under "All metrics".
MAIN_COSTS = ("ratio", "Params", "MACs")


def to_markdown(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig, footer: list[str] | None = None) -> str:
    """The markdown: a main table (the row, the primary metric ours ± std and the paper's, its 95 % CI, the
    difference from the reference row, the latency ratio, parameters, MACs and n; a table's text columns after
    the row), then "All metrics" (every other metric, ours beside the paper's, and the latency) when there is more to show; the footer
    under them. ``footer``: the provenance lines (:func:`ablate.tables.provenance.provenance` of ``runs`` when
    None). A table without any paper number (an ad-hoc sweep) has no paper columns and no τ line."""
    lines = [f"# {table.title}", ""]
    if not len(summary):
        lines.append("No finished runs yet.")
    else:
        main: dict[str, list[str]] = {"Row": list(summary["name"])}
        for key, label in (table.get("text_columns") or {}).items():  # what the row is (DGFN Table II's "Data")
            main[label] = list(summary[key])
        main.update(metric_columns(summary, table, [table.primary]))
        sig_columns, sig_lines = significance(summary, runs, table)
        main.update(sig_columns)
        cost_columns, cost_lines = costs(summary, runs, table)
        main.update(
            {k: v for k, v in cost_columns.items() if any(k.endswith(c) or k.startswith(c) for c in MAIN_COSTS)}
        )
        main["n"] = [str(n) if n else "paper only" for n in summary["n"]]
        lines.append(pd.DataFrame(main).to_markdown(index=False, disable_numparse=True))
        others = [k for k in table.metrics if k not in COSTS and k != table.primary]
        rest: dict[str, list[str]] = {"Row": list(summary["name"])}
        rest.update(metric_columns(summary, table, others))
        rest.update({k: v for k, v in cost_columns.items() if k not in main and set(v) != {"—"}})
        if len(rest) > 1:
            lines += ["", "All metrics:", "", pd.DataFrame(rest).to_markdown(index=False, disable_numparse=True)]
        lines.append("")
        tau, n = kendall(summary, table.primary)
        label = table.metrics.get(table.primary, table.primary)
        if summary[f"{table.primary}_paper"].notna().any():
            lines.append(
                f"Kendall τ between our ranking and the paper's on {label}: "
                + ("n/a (fewer than 2 rows with both)" if np.isnan(tau) else f"{tau:.2f} over {n} rows")
                + "."
            )
        lines += sig_lines + cost_lines
    done = set(summary.loc[summary["n"] > 0, "row"]) if len(summary) else set()
    missing = [
        spec.get("name", spec["row"]) for spec in table.rows if spec["row"] not in done and not spec.get("paper_only")
    ]
    if missing:
        lines.append(f"Rows without a finished run: {', '.join(missing)}.")
    scales = sorted(runs["scale"].unique()) if len(runs) else []
    lines += [
        "",
        f"mean ± std over seeds (n runs per row); scale: {', '.join(scales) or '—'}. "
        "Bold: best in its column. "
        + " ".join(provenance(runs) if footer is None else footer)
        + " Regenerated by `python -m ablate.report`; do not edit by hand.",
        "",
    ]
    return "\n".join(lines)


def plot(summary: pd.DataFrame, table: DictConfig) -> Figure:
    """A bar chart of the primary metric per row: ours (mean, its 95% CI as error bar) beside the paper's."""
    key = table.primary
    label = table.metrics.get(key, key)
    fig, ax = plt.subplots(figsize=(max(4.0, 1.3 * len(summary) + 2), 3.2))
    x = np.arange(len(summary))
    if len(summary):
        mean = summary[f"{key}_mean"]
        err = np.stack([(mean - summary[f"{key}_lo"]).fillna(0), (summary[f"{key}_hi"] - mean).fillna(0)])
        ax.bar(x - 0.2, mean, 0.4, yerr=err, capsize=3, label="ours (95% CI)")
        if summary[f"{key}_paper"].notna().any():
            ax.bar(x + 0.2, summary[f"{key}_paper"], 0.4, label="paper", alpha=0.7)
        ax.set_xticks(x, summary["name"], rotation=20, ha="right")
    ax.set_ylabel(label)
    ax.set_title(table.title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def write_rows(
    cfg: DictConfig,
    table: DictConfig,
    runs: pd.DataFrame,
    tracker: Tracker | None,
    parent_run: str | None,
    results_dir: str | Path,
    footer: list[str] | None = None,
) -> list[Path]:
    """Write ``results/<table>.md`` and ``.png``, and its numbers as ``.csv`` and ``.tex``
    (:mod:`ablate.tables.export`), from the runs; log them to ``parent_run`` if given."""
    runs = under_condition(runs, table)
    summary = summarise(runs, table)
    out = Path(results_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, png = out / f"{table.name}.md", out / f"{table.name}.png"
    md.write_text(to_markdown(summary, runs, table, footer))
    numbers = write_numbers(summary, runs, table, out)
    fig = plot(summary, table)
    fig.savefig(png, dpi=100, metadata={"Software": None})
    if parent_run and tracker is not None:
        tracker.log_figure(parent_run, fig, f"{table.name}.png")
        for path in (md, *numbers):
            tracker.log_artifact(parent_run, path)
    plt.close(fig)
    return [md, png, *numbers]
