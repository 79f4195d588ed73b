"""Tables whose rows are test conditions and whose columns are model x metric (DGFN Table I's shape).

The runs of such a table were each tested under ``task.eval_conditions`` and hold ``<condition>/<metric>``
(:class:`ablate.tasks.base.FusionTask`). The experiment's ``table`` names the models (``rows``), the conditions in
the paper's order with the paper's numbers per model (``conditions: [{condition, name, paper: {row: {metric:
value}}}]``), the metrics, the ``primary`` metric and ``primary_condition`` under which the models are compared.

Written: ``results/<table>.md`` (mean ± std over seeds, the paper's number beside ours, the better model per
condition and metric bold, Kendall's τ per column between our ordering of the conditions and the paper's; under it
one row per model with the 95 % CI of the primary metric, its difference from the reference model, latency,
parameters and MACs), ``<table>.png`` (the primary metric per condition and model), ``<table>_robustness.png``
(the primary metric against the corruption's severity, per model, from the severity variants
``<condition>-s<severity>``), one more table per entry of ``table.also`` (other metrics of the same runs, e.g. the
mean gate per condition) and a copy of each run artifact of ``table.artifacts``.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, cast

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from mlflow.exceptions import MlflowException  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from ablate.store import Tracker  # noqa: E402
from ablate.tables.columns import costs, significance  # noqa: E402
from ablate.tables.export import write_numbers  # noqa: E402
from ablate.tables.provenance import provenance  # noqa: E402
from ablate.tables.spec import COSTS  # noqa: E402
from ablate.tables.summary import fmt, kendall, summarise  # noqa: E402

VARIANT = re.compile(r"^(?P<condition>.+)-s(?P<severity>[0-9.]+(?:e[-+]?[0-9]+)?)/(?P<metric>.+)$")


def flat_spec(table: DictConfig) -> DictConfig:
    """The table as one row per model with one metric per condition and metric (``<condition>/<metric>``), the
    paper's numbers flattened alike and the primary metric taken under ``primary_condition``."""
    conditions = list(table.get("conditions") or [])
    if not conditions:
        raise ValueError(f"table.conditions: the conditions layout of '{table.name}' needs its list of conditions")
    if table.get("primary_condition") not in [c["condition"] for c in conditions]:
        raise ValueError(
            f"table.primary_condition: {table.get('primary_condition')!r} is not one of the table's "
            f"conditions {[c['condition'] for c in conditions]}"
        )
    metrics = {
        f"{c['condition']}/{k}": f"{label} ({c['name']})"
        for c in conditions
        for k, label in table.metrics.items()
        if k not in COSTS
    }
    rows = [
        {
            "row": r["row"],
            "name": r.get("name", r["row"]),
            "paper": {
                f"{c['condition']}/{k}": v
                for c in conditions
                for k, v in ((c.get("paper") or {}).get(r["row"]) or {}).items()
            },
        }
        for r in table.rows
    ]
    flat = cast(dict[str, Any], OmegaConf.to_container(table, resolve=True))
    flat.update(
        rows=rows,
        metrics={**metrics, **{k: v for k, v in table.metrics.items() if k in COSTS}},
        primary=f"{table.primary_condition}/{table.primary}",
    )
    return cast(DictConfig, OmegaConf.create(flat))


def condition_rows(summary: pd.DataFrame, table: DictConfig, bold: bool = True) -> tuple[pd.DataFrame, list[str]]:
    """The markdown frame: one row per condition, per model and metric ours (mean ± std) and the paper's, the
    better model bold (``bold``); a last row of Kendall τ per column. Returns it and its footer lines."""
    conditions = list(table.conditions)
    metrics = {k: v for k, v in table.metrics.items() if k not in COSTS}
    with_paper = any(c.get("paper") for c in conditions)
    frame: dict[str, list[str]] = {
        "Test input": [c["name"] for c in conditions] + (["Kendall τ vs paper (n)"] if with_paper else [])
    }
    models = list(zip(summary["row"], summary["name"])) if len(summary) else []
    for row, name in models:
        rec = summary[summary["row"] == row].iloc[0]
        for k, label in metrics.items():
            ours, paper, cells, pcells = [], [], [], []
            for c in conditions:
                key = f"{c['condition']}/{k}"
                mean, std = rec.get(f"{key}_mean", np.nan), rec.get(f"{key}_std", np.nan)
                rivals = [summary[f"{key}_mean"].max()] if f"{key}_mean" in summary else [np.nan]
                best = bold and len(models) > 1 and not np.isnan(mean) and mean == rivals[0]
                cells.append(fmt(mean, std, best))
                ours.append(mean)
                paper.append(rec.get(f"{key}_paper", np.nan))
                pcells.append(fmt(paper[-1], np.nan, False))
            tau, n = kendall(pd.DataFrame({f"{k}_mean": ours, f"{k}_paper": paper}), k)
            frame[f"{name}: {label} (ours)"] = cells + (
                ["n/a" if np.isnan(tau) else f"{tau:.2f} ({n})"] if with_paper else []
            )
            if not all(np.isnan(paper)):
                frame[f"{name}: {label} (paper)"] = pcells + [""]
    lines = (["Bold: the better model under that test input on that metric."] if bold else []) + (
        ["Kendall τ: between our ordering of the test inputs and the paper's, per column (n conditions with both)."]
        if with_paper
        else []
    )
    return pd.DataFrame(frame), lines


def model_rows(summary: pd.DataFrame, runs: pd.DataFrame, flat: DictConfig) -> tuple[pd.DataFrame, list[str]]:
    """One row per model: the primary metric's 95 % CI and difference from the reference model, and the costs.
    Seeds that disagree are looked for in the metrics under the primary condition."""
    condition = flat.primary.split("/", 1)[0]
    focus = cast(DictConfig, OmegaConf.merge(flat, {"metrics": None}))
    focus.metrics = {k: v for k, v in flat.metrics.items() if k.startswith(f"{condition}/") or k in COSTS}
    sig, sig_lines = significance(summary, runs, focus)
    cost, cost_lines = costs(summary, runs, flat)
    frame = {"Model": list(summary["name"]), **sig, **cost, "n": [str(n) for n in summary["n"]]}
    return pd.DataFrame(frame), sig_lines + cost_lines


def to_markdown(
    summary: pd.DataFrame,
    runs: pd.DataFrame,
    table: DictConfig,
    flat: DictConfig,
    per_model: bool = True,
    footer: list[str] | None = None,
) -> str:
    lines = [f"# {table.title}", ""]
    if not len(summary):
        lines.append("No finished runs yet.")
    else:
        frame, notes = condition_rows(summary, table, bold=per_model)
        lines += [frame.to_markdown(index=False, disable_numparse=True), "", *notes]
        if per_model:
            frame, notes = model_rows(summary, runs, flat)
            label = flat.metrics.get(flat.primary, flat.primary)
            lines += [
                "",
                f"Per model, on {label}:",
                "",
                frame.to_markdown(index=False, disable_numparse=True),
                "",
                *notes,
            ]
    done = set(summary["row"]) if len(summary) else set()
    missing = [spec.get("name", spec["row"]) for spec in table.rows if spec["row"] not in done]
    if missing:
        lines.append(f"Rows without a finished run: {', '.join(missing)}.")
    scales = sorted(runs["scale"].unique()) if len(runs) else []
    lines += [
        "",
        f"mean ± std over seeds (n runs per model); scale: {', '.join(scales) or '—'}. "
        + (f"{table.note} " if table.get("note") else "")
        + " ".join(provenance(runs) if footer is None else footer)
        + " Regenerated by `python -m ablate.report`; do not edit by hand.",
        "",
    ]
    return "\n".join(lines)


def plot(summary: pd.DataFrame, table: DictConfig) -> Figure:
    """The primary metric per condition: ours per model (mean, 95 % CI as error bar), the paper's as markers."""
    conditions, key = list(table.conditions), table.primary
    fig, ax = plt.subplots(figsize=(max(5.0, 1.1 * len(conditions) + 2), 3.4))
    x, width = np.arange(len(conditions)), 0.8 / max(len(summary), 1)
    for j, (_, rec) in enumerate(summary.iterrows()):
        keys = [f"{c['condition']}/{key}" for c in conditions]
        mean = np.array([rec.get(f"{k}_mean", np.nan) for k in keys], float)
        err = np.stack(
            [
                np.nan_to_num(mean - np.array([rec.get(f"{k}_lo", np.nan) for k in keys], float)),
                np.nan_to_num(np.array([rec.get(f"{k}_hi", np.nan) for k in keys], float) - mean),
            ]
        )
        pos = x - 0.4 + width * (j + 0.5)
        bars = ax.bar(pos, mean, width, yerr=err, capsize=2, label=f"{rec['name']} (ours)")
        ax.plot(
            pos,
            [rec.get(f"{k}_paper", np.nan) for k in keys],
            ls="none",
            marker="_",
            ms=10,
            mew=2,
            color=bars.patches[0].get_facecolor() if bars.patches else "k",
        )
    ax.plot([], [], ls="none", marker="_", ms=10, mew=2, color="k", label="paper (per model, its colour)")
    ax.set_xticks(x, [c["name"] for c in conditions], rotation=25, ha="right", fontsize=7)
    ax.set_ylabel(table.metrics.get(key, key))
    ax.set_title(table.title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def curves(runs: pd.DataFrame, table: DictConfig, specs: dict) -> dict[str, dict[str, dict[float, pd.Series]]]:
    """{condition: {row: {severity: values over seeds}}} of the primary metric, for every condition with severity
    variants in the runs; severity 0 is the condition whose spec is empty (the normal input), 1 the condition."""
    found: dict[str, set[float]] = {}
    for col in runs.columns:
        m = VARIANT.match(str(col))
        if m and m["metric"] == table.primary:
            found.setdefault(m["condition"], set()).add(float(m["severity"]))
    normal = next((n for n, spec in specs.items() if not spec), None)
    out: dict = {}
    for cond in [c["condition"] for c in table.conditions if c["condition"] in found]:
        keys = {1.0: f"{cond}/{table.primary}", **{s: f"{cond}-s{s:g}/{table.primary}" for s in found[cond]}}
        if normal:
            keys[0.0] = f"{normal}/{table.primary}"
        out[cond] = {
            r["row"]: {
                s: runs.loc[runs["row"] == r["row"], k].dropna() if k in runs else pd.Series(dtype=float)
                for s, k in sorted(keys.items())
            }
            for r in table.rows
        }
    return out


def plot_curves(data: dict, table: DictConfig) -> Figure:
    """Robustness curves: per condition a panel, per model mean ± std over seeds against the severity."""
    names = {c["condition"]: c["name"] for c in table.conditions}
    names_rows = {r["row"]: r.get("name", r["row"]) for r in table.rows}
    fig, axes = plt.subplots(1, len(data), figsize=(3.2 * len(data) + 0.6, 3.0), squeeze=False, sharey=True)
    for ax, (cond, rows) in zip(axes[0], data.items()):
        for row, points in rows.items():
            xs = [s for s, v in points.items() if len(v)]
            mean = np.array([points[s].mean() for s in xs])
            std = np.array([points[s].std(ddof=1) if len(points[s]) > 1 else 0.0 for s in xs])
            (line,) = ax.plot(xs, mean, "o-", ms=3, label=names_rows.get(row, row))
            ax.fill_between(xs, mean - std, mean + std, alpha=0.2, color=line.get_color())
        ax.set_title(names.get(cond, cond), fontsize=8)
        ax.set_xlabel("severity (0: normal input, 1: the table's)", fontsize=7)
    axes[0, 0].set_ylabel(table.metrics.get(table.primary, table.primary))
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{table.title}: robustness curves", fontsize=9)
    fig.tight_layout()
    return fig


def copy_artifacts(tracker: Tracker, runs: pd.DataFrame, table: DictConfig, out: Path) -> list[Path]:
    """Each ``table.artifacts`` entry ({row, artifact, as}): the artifact of the row's lowest-seed run, copied to
    ``out/<as>`` (from the run it was reused from, which holds the artifacts)."""
    written = []
    for spec in table.get("artifacts") or []:
        sel = runs[runs["row"] == spec["row"]].sort_values("seed") if len(runs) else runs
        if sel.empty:
            continue
        run = tracker.get_run(sel["run_id"].iloc[0])
        source = run.data.tags.get("reused_from", run.info.run_id)
        with tempfile.TemporaryDirectory() as tmp:
            try:
                path = tracker.download_artifact(source, spec["artifact"], tmp)
            except MlflowException:  # a run without the artifact (a failed figure; not found) leaves no copy
                continue
            shutil.copyfile(path, out / spec["as"])
        written.append(out / spec["as"])
    return written


def write_conditions(
    cfg: DictConfig,
    table: DictConfig,
    runs: pd.DataFrame,
    tracker: Tracker | None,
    parent_run: str | None,
    results_dir: str | Path,
    footer: list[str] | None = None,
) -> list[Path]:
    """Write the condition-rows table of ``table`` and its figures, sub-tables and artifacts; return the paths."""
    out = Path(results_dir)
    out.mkdir(parents=True, exist_ok=True)
    flat = flat_spec(table)
    summary = summarise(runs, flat)
    md, png = out / f"{table.name}.md", out / f"{table.name}.png"
    md.write_text(to_markdown(summary, runs, table, flat, footer=footer))
    written = [md, png, *write_numbers(summary, runs, flat, out)]  # per model, a column per condition and metric
    figures = {png: plot(summary, table)}
    specs = (
        cast(dict, OmegaConf.to_container(cfg.task.get("eval_conditions") or {}, resolve=True)) if "task" in cfg else {}
    )
    data = curves(runs, table, specs) if len(runs) else {}
    if data:
        figures[out / f"{table.name}_robustness.png"] = plot_curves(data, table)
        written.append(out / f"{table.name}_robustness.png")
    for path, fig in figures.items():
        fig.savefig(path, dpi=100, metadata={"Software": None})
        if parent_run and tracker is not None:
            tracker.log_figure(parent_run, fig, path.name)
        plt.close(fig)
    for extra in table.get("also") or []:
        sub = cast(
            DictConfig,
            OmegaConf.merge(
                table,
                {
                    "name": extra["name"],
                    "title": extra["title"],
                    "primary": next(iter(extra["metrics"])),
                    "note": extra.get("note"),
                },
            ),
        )
        sub.metrics = extra["metrics"]
        sub.conditions = [{k: v for k, v in c.items() if k != "paper"} for c in table.conditions]
        sub_flat = flat_spec(sub)
        path = out / f"{extra['name']}.md"
        path.write_text(to_markdown(summarise(runs, sub_flat), runs, sub, sub_flat, per_model=False, footer=footer))
        written.append(path)
    if tracker is not None:  # from records: the copies already beside the table stay as they are
        written += copy_artifacts(tracker, runs, table, out)
    if parent_run and tracker is not None:
        for path in written:
            if path.suffix == ".md":
                tracker.log_artifact(parent_run, path)
    return written
