"""Tables from runs: MLflow ``search_runs`` -> pandas -> ``results/<table>.md`` and ``results/<table>.png``.

``python -m ablate.report`` regenerates every table that has runs; ``python -m ablate.report
experiment=chinet_table2`` just one (other ``key=value`` overrides, e.g. ``logger.tracking_uri=...``, apply too).
A multirun writes its table at the end by itself. Only FINISHED job runs count (per row and seed the latest, at
the scale of the latest run), so a failed job never becomes a row; a row with no finished run is listed under the
table instead. The same runs give the same bytes: no timestamps, rows in the paper's order, PNG written without
metadata.

Two layouts (``table.layout``): ``rows`` (the default) has a row per trained model; ``conditions`` (DGFN Table I's
shape) has a row per test condition and columns model x metric, from runs tested under ``task.eval_conditions``
(:mod:`ablate.report_conditions`). A row with ``paper_only: true`` is another system of the paper, listed with the
paper's numbers and never run; ``table.text_columns`` ({key: label}) adds text columns read from each row. A
``rows`` table with ``primary_condition`` shows its metrics under that test condition (``<condition>/<metric>``).
"""
from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from scipy.stats import kendalltau  # noqa: E402

from ablate.provenance import evaluators, stale  # noqa: E402
from ablate.significance import BOOTSTRAP_FROM, COLLAPSE_RATIO, RESAMPLES, difference, disagreeing_seeds, \
    mean_ci  # noqa: E402
from ablate.tracking import KIND_JOB, KIND_SWEEP, Tracker, retry  # noqa: E402

CONF = Path(__file__).resolve().parent.parent / "conf"
#: Cost columns every table gets after its metrics (from ``python -m ablate.latency``, which a multirun runs at its
#: end); a table may list one itself to give it its paper's label and numbers (ChiNet's "Comp Time (ms)").
COSTS = {"latency_ms": "Latency (ms)", "params_m": "Params (M)", "macs_g": "MACs (G)"}
LOWER_IS_BETTER = {"comp_time_ms", *COSTS}


def collect(tracker: Tracker, table: str) -> pd.DataFrame:
    """One row per (row, seed) of ``table``: its latest FINISHED job run, at the scale of the latest such run.

    A rerun after a config change (another recipe, another dataset) supersedes the earlier run of the same row and
    seed instead of counting as one more seed; runs at another scale (a smoke sweep beside the default-scale table)
    stay in the store and out of the table."""
    exp = retry(tracker.client.get_experiment_by_name, table)
    if exp is None:
        return pd.DataFrame()
    runs = tracker.runs(exp.experiment_id, f"attributes.status = 'FINISHED' and tags.kind = '{KIND_JOB}'")
    records = [{"row": r.data.tags.get("row", "?"), "seed": r.data.tags.get("seed", "?"),
                "scale": r.data.tags.get("scale", "?"), "config_hash": r.data.tags.get("config_hash", r.info.run_id),
                "git_commit": r.data.tags.get("git_commit", "unknown"), "run_id": r.info.run_id,
                "evaluator": r.data.tags.get("evaluator", ""),
                "targets": " ".join(sorted({v for k, v in r.data.params.items() if k.endswith("_target_")})),
                "start": r.info.start_time, **r.data.metrics} for r in runs]
    if not records:
        return pd.DataFrame()
    df = pd.DataFrame.from_records(records).sort_values(["start", "config_hash"], kind="stable")
    df = df[df["scale"] == df["scale"].iloc[-1]]
    return df.drop_duplicates(["row", "seed"], keep="last").drop(columns="start").reset_index(drop=True)


def under_condition(runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """``runs`` with the metrics of ``table.primary_condition`` (``<condition>/<metric>``) as the plain metrics."""
    condition = table.get("primary_condition")
    if not condition or not len(runs):
        return runs
    prefix = f"{condition}/"
    moved = {c: c[len(prefix):] for c in runs.columns if str(c).startswith(prefix)}
    return runs.drop(columns=[c for c in moved.values() if c in runs]).rename(columns=moved)


def summarise(runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """Per table row (in the paper's order): mean, std, n and 95 % CI (``ablate.significance.mean_ci``) of each
    metric over seeds, and the paper's value."""
    rows = list(table.rows) or [{"row": r, "name": r, "paper": {}} for r in sorted(runs["row"].unique())]
    out = []
    for spec in rows:
        sel = runs[runs["row"] == spec["row"]] if len(runs) else runs
        if sel.empty and not spec.get("paper_only"):
            continue
        rec = {"row": spec["row"], "name": spec.get("name", spec["row"]), "n": len(sel),
               **{key: str(spec.get(key, "")) for key in table.get("text_columns") or {}}}
        for key in table.metrics:
            values = sel[key].dropna() if key in sel else pd.Series(dtype=float)
            rec[f"{key}_mean"] = values.mean() if len(values) else np.nan
            rec[f"{key}_std"] = values.std(ddof=1) if len(values) > 1 else np.nan
            ci = mean_ci(values)
            rec[f"{key}_lo"], rec[f"{key}_hi"] = ci.lo, ci.hi
            rec[f"{key}_paper"] = (spec.get("paper") or {}).get(key, np.nan)
        out.append(rec)
    return pd.DataFrame.from_records(out)


def _fmt(mean: float, std: float, bold: bool) -> str:
    if np.isnan(mean):
        return "—"
    text = f"{mean:.2f}" + ("" if np.isnan(std) else f" ± {std:.2f}")
    return f"**{text}**" if bold else text


def _best(values: pd.Series, key: str) -> float:
    values = values.dropna()
    if values.empty:
        return np.nan
    return values.min() if key in LOWER_IS_BETTER else values.max()


def kendall(summary: pd.DataFrame, key: str) -> tuple[float, int]:
    """Kendall's tau between our row ranking and the paper's on ``key``, and the number of rows compared."""
    both = summary[[f"{key}_mean", f"{key}_paper"]].dropna() if len(summary) else pd.DataFrame()
    if len(both) < 2:
        return np.nan, len(both)
    return float(kendalltau(both.iloc[:, 0], both.iloc[:, 1]).statistic), len(both)


def reference(summary: pd.DataFrame, table: DictConfig) -> str | None:
    """The row the others are compared with: ``table.reference`` (a row, or a list of rows of which the best on
    the primary metric is taken, e.g. SMoE Table 1's better single-modal expert); the first row by default."""
    if not len(summary):
        return None
    ref = table.get("reference")
    candidates = [ref] if isinstance(ref, str) else list(ref or [summary["row"].iloc[0]])
    sel = summary[summary["row"].isin(candidates)]
    if sel.empty:
        return None
    means = sel[f"{table.primary}_mean"]
    best = _best(means, table.primary)
    return str(sel["row"][means == best].iloc[0]) if not np.isnan(best) else str(sel["row"].iloc[0])


def _per_seed(runs: pd.DataFrame, row: str, key: str) -> pd.Series:
    sel = runs[runs["row"] == row] if key in runs else runs.iloc[0:0]
    return (sel.set_index("seed")[key] if len(sel) else pd.Series(dtype=float)).dropna()


def _signed(x: float) -> str:
    return f"{x:+.2f}".replace("-", "−")


def significance(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> tuple[dict, list[str]]:
    """The primary metric's CI column and difference-from-reference column, and the footer lines that explain
    them: the test used, whether the top row is ahead of the second beyond seed noise, and disagreeing seeds."""
    key, label = table.primary, table.metrics.get(table.primary, table.primary)
    ref = reference(summary, table)
    if ref is None:
        return {}, []
    ref_name = str(summary.loc[summary["row"] == ref, "name"].iloc[0])
    ref_values = _per_seed(runs, ref, key)
    cis, deltas, tests = [], [], set()
    for row, lo, hi in zip(summary["row"], summary[f"{key}_lo"], summary[f"{key}_hi"]):
        cis.append("—" if np.isnan(lo) else f"[{lo:.2f}, {hi:.2f}]")
        if row == ref:
            deltas.append("reference")
            continue
        d = difference(_per_seed(runs, row, key), ref_values)
        if np.isnan(d.ci.lo):
            deltas.append("—" if np.isnan(d.delta) else _signed(d.delta))
            continue
        tests.add(d.test)
        deltas.append(f"{_signed(d.delta)} [{_signed(d.ci.lo)}, {_signed(d.ci.hi)}]" + (" *" if d.significant else ""))
    columns = {f"{label} 95% CI": cis, f"Δ {label} vs {ref_name} [95% CI]": deltas}
    lines = [f"95% CI: of the mean over seeds, Student's t for n < {BOOTSTRAP_FROM}, a percentile bootstrap over "
             f"seeds ({RESAMPLES} resamples) from n = {BOOTSTRAP_FROM}. Δ: difference from {ref_name} on {label} "
             f"({', '.join(sorted(tests)) or 'no test: too few seeds'}; paired over the seeds two rows share); "
             "*: its 95% CI excludes 0."]
    ranked = summary.dropna(subset=[f"{key}_mean"]).sort_values(f"{key}_mean", ascending=key in LOWER_IS_BETTER,
                                                                kind="stable")
    if len(ranked) >= 2:
        (top, top_name), (second, second_name) = [tuple(r) for r in ranked[["row", "name"]].iloc[:2].to_numpy()]
        d = difference(_per_seed(runs, top, key), _per_seed(runs, second, key))
        verdict = ("n/a (too few seeds)" if np.isnan(d.ci.lo) else
                   f"{_signed(d.delta)} [{_signed(d.ci.lo)}, {_signed(d.ci.hi)}], {d.test}, p = {d.p:.3f}: "
                   + ("ahead beyond seed noise" if d.significant else "not separable from seed noise"))
        lines.append(f"Top row {top_name} against the second, {second_name}, on {label}: {verdict}.")
    for row, name in zip(summary["row"], summary["name"]):
        for k, lab in table.metrics.items():
            if k in LOWER_IS_BETTER:
                continue
            for seed, v, med in disagreeing_seeds(_per_seed(runs, row, k)):
                lines.append(f"**Seeds disagree**: {name}, {lab}, seed {seed} gives {v:.2f} against a median of "
                             f"{med:.2f} over its other seeds (below {COLLAPSE_RATIO:.0%} of it); the row's mean "
                             "hides a failed seed.")
    return columns, lines


def costs(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> tuple[dict, list[str]]:
    """Latency (median [interquartile range] over the interleaved rounds, and its ratio to the reference row),
    parameters and MACs per row, with a footer saying how latency was measured and warning of a loaded machine."""
    if not len(summary):
        return {}, []
    columns: dict[str, list[str]] = {}

    def per_row(key: str) -> list[float]:
        return [_per_seed(runs, row, key).mean() if key in runs else np.nan for row in summary["row"]]

    med, q1, q3 = per_row("latency_ms"), per_row("latency_q1_ms"), per_row("latency_q3_ms")
    label = table.metrics.get("latency_ms", COSTS["latency_ms"])
    best = np.nanmin(med) if not np.all(np.isnan(med)) else np.nan
    columns[f"{label} (ours)"] = ["—" if np.isnan(m) else (f"**{m:.2f}**" if m == best else f"{m:.2f}")
                                  + f" [{a:.2f}, {b:.2f}]" for m, a, b in zip(med, q1, q3)]
    paper = summary["latency_ms_paper"] if "latency_ms_paper" in summary else pd.Series(dtype=float)
    if paper.notna().any():
        columns[f"{label} (paper)"] = [_fmt(v, np.nan, v == _best(paper, "latency_ms")) for v in paper]
    ref = reference(summary, table)
    ref_med = med[list(summary["row"]).index(ref)] if ref is not None else np.nan
    if not np.isnan(ref_med):
        columns[f"{label} ratio"] = ["—" if np.isnan(m) else f"{m / ref_med:.2f}×" for m in med]
    for key in ("params_m", "macs_g"):
        values = per_row(key)
        if not np.all(np.isnan(values)):
            columns[table.metrics.get(key, COSTS[key])] = ["—" if np.isnan(v) else f"{v:.2f}" for v in values]
    lines = []
    if np.all(np.isnan(med)):
        lines.append(f"{label}: not measured yet (`python -m ablate.latency experiment={table.name}`).")
        return columns, lines
    load, cores = runs.get("latency_load", pd.Series(dtype=float)).max(), runs["latency_cores"].max()
    rounds = f"{label}: median [interquartile range] of one forward pass at batch 1, every row timed side by side " \
             "in one process, interleaved (`python -m ablate.latency`); ratio to the reference row. " \
             f"Load average up to {load:.1f} on {cores:.0f} cores."
    lines.append(rounds + (f" **Loaded machine**: the load exceeded the {cores:.0f} available cores while timing; "
                           "rerun `python -m ablate.latency` on a quiet machine." if load > cores else ""))
    return columns, lines


def provenance(runs: pd.DataFrame) -> list[str]:
    """The commits the table's runs were made at (the ``git_commit`` tag), a warning when they differ, and one
    when code the runs' configs build (``ablate.provenance``) changed since a run's commit."""
    if not len(runs) or "git_commit" not in runs:
        return []
    counts = runs["git_commit"].fillna("unknown").value_counts().sort_index()
    named = ", ".join(f"{c[:12]}{'-dirty' if c.endswith('-dirty') else ''} ({n} runs)" for c, n in counts.items())
    lines = [f"Runs made at commit {named}."]
    if len(counts) > 1:
        lines.append(f"**Mixed commits**: the rows come from {len(counts)} commits.")
    targets = set(" ".join(runs["targets"].fillna("")).split()) if "targets" in runs else set()
    shas = {c.removesuffix("-dirty") for c in counts.index} - {"unknown"}
    changed = stale(shas, targets) if targets else {}
    for sha, files in changed.items():
        dirty = any(c == f"{sha}-dirty" for c in counts.index)
        shown = ", ".join(files[:6]) + (f" and {len(files) - 6} more" if len(files) > 6 else "")
        lines.append(f"**Code changed since {sha[:12]}**" + (" (some runs made with uncommitted changes on top)"
                                                            if dirty else "")
                     + f" in what its runs build: {shown}; their numbers may not be what the code gives today.")
    if targets and not changed:
        lines.append("No code the runs build has changed since their commits.")
    return lines + metric_changed(runs, targets)


def metric_changed(runs: pd.DataFrame, targets: set[str]) -> list[str]:
    """A line per metric the runs' code builds whose evaluator today (``ablate.provenance.evaluators``) is not the
    one some runs were scored with (their ``evaluator`` tag; none on runs made before the tag)."""
    used = runs["evaluator"].fillna("") if "evaluator" in runs else pd.Series([""] * len(runs), dtype=str)
    lines = []
    for module, current in (evaluators(targets) if targets else {}).items():
        off = used[[current not in tag.split(", ") for tag in used]]
        if off.empty:
            continue
        counts = off.value_counts().sort_index()
        was = ", ".join(f"{tag or 'no recorded evaluator'}: {n}" for tag, n in counts.items())
        lines.append(f"**Metric changed since these runs**: {module} now follows {current} "
                     f"(ablate/metrics/__init__.py), and {len(off)} of {len(runs)} runs were scored otherwise ({was}); "
                     "rerun them (`force=true`) to compare with the paper.")
    return lines


def to_markdown(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> str:
    """The markdown table: ours (mean ± std over seeds) beside the paper's number, best value of a column bold;
    the primary metric's 95% CI and its difference from the reference row; provenance under it."""
    columns: dict[str, list[str]] = {"Row": list(summary["name"]) if len(summary) else []}
    for key, label in (table.get("text_columns") or {}).items():
        columns[label] = list(summary[key]) if len(summary) else []
    for key, label in table.metrics.items():
        if key in COSTS:
            continue
        best = _best(summary[f"{key}_mean"], key) if len(summary) else np.nan
        columns[f"{label} (ours)"] = [_fmt(m, s, m == best) for m, s in
                                      zip(summary[f"{key}_mean"], summary[f"{key}_std"])] if len(summary) else []
        paper = summary[f"{key}_paper"] if len(summary) else pd.Series(dtype=float)
        if paper.notna().any():
            pbest = _best(paper, key)
            columns[f"{label} (paper)"] = [_fmt(p, np.nan, p == pbest) for p in paper]
    sig_columns, sig_lines = significance(summary, runs, table)
    columns.update(sig_columns)
    cost_columns, cost_lines = costs(summary, runs, table)
    columns.update(cost_columns)
    columns["n"] = [str(n) if n else "paper only" for n in summary["n"]] if len(summary) else []
    lines = [f"# {table.title}", ""]
    if len(summary):
        lines.append(pd.DataFrame(columns).to_markdown(index=False, disable_numparse=True))
    else:
        lines.append("No finished runs yet.")
    tau, n = kendall(summary, table.primary)
    label = table.metrics.get(table.primary, table.primary)
    lines += ["", f"Kendall τ between our ranking and the paper's on {label}: "
              + ("n/a (fewer than 2 rows with both)" if np.isnan(tau) else f"{tau:.2f} over {n} rows") + "."]
    lines += sig_lines + cost_lines
    done = set(summary.loc[summary["n"] > 0, "row"]) if len(summary) else set()
    missing = [spec.get("name", spec["row"]) for spec in table.rows if spec["row"] not in done
               and not spec.get("paper_only")]
    if missing:
        lines.append(f"Rows without a finished run: {', '.join(missing)}.")
    scales = sorted(runs["scale"].unique()) if len(runs) else []
    lines += ["", f"mean ± std over seeds (n runs per row); scale: {', '.join(scales) or '—'}. "
              "Bold: best in its column. " + " ".join(provenance(runs))
              + " Regenerated by `python -m ablate.report`; do not edit by hand.", ""]
    return "\n".join(lines)


def plot(summary: pd.DataFrame, table: DictConfig):
    """A bar chart of the primary metric per row: ours (mean, its 95% CI as error bar) beside the paper's."""
    key = table.primary
    label = table.metrics.get(key, key)
    fig, ax = plt.subplots(figsize=(max(4.0, 1.3 * len(summary) + 2), 3.2))
    x = np.arange(len(summary))
    if len(summary):
        mean = summary[f"{key}_mean"]
        err = np.stack([(mean - summary[f"{key}_lo"]).fillna(0), (summary[f"{key}_hi"] - mean).fillna(0)])
        ax.bar(x - 0.2, mean, 0.4, yerr=err, capsize=3, label="ours (95% CI)")
        ax.bar(x + 0.2, summary[f"{key}_paper"], 0.4, label="paper", alpha=0.7)
        ax.set_xticks(x, summary["name"], rotation=20, ha="right")
    ax.set_ylabel(label)
    ax.set_title(table.title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def table_spec(cfg: DictConfig) -> DictConfig:
    """``cfg.table`` with ``metrics`` and ``primary`` falling back to the task's when the table leaves them null."""
    table = OmegaConf.to_container(cfg.table, resolve=True)
    table["metrics"] = table.get("metrics") or OmegaConf.to_container(cfg.get("metrics") or {}, resolve=True)
    table["primary"] = table.get("primary") or cfg.get("primary") or next(iter(table["metrics"]), None)
    table["metrics"] = {**table["metrics"], **{k: v for k, v in COSTS.items() if k not in table["metrics"]}}
    return OmegaConf.create(table)


def write_table(cfg: DictConfig, tracker: Tracker, parent_run: str | None = None,
                results_dir: str | Path = "results") -> list[Path]:
    """Write ``results/<table>.md`` and ``.png`` from the runs; log the figure to ``parent_run`` if given."""
    table = table_spec(cfg)
    runs = collect(tracker, table.name)
    if table.get("layout", "rows") == "conditions":
        from ablate.report_conditions import write_conditions

        return write_conditions(cfg, table, runs, tracker, parent_run, results_dir)
    if table.get("layout", "rows") != "rows":
        raise ValueError(f"table.layout: {table.layout!r} is not one of rows, conditions")
    runs = under_condition(runs, table)
    summary = summarise(runs, table)
    out = Path(results_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, png = out / f"{table.name}.md", out / f"{table.name}.png"
    md.write_text(to_markdown(summary, runs, table))
    fig = plot(summary, table)
    fig.savefig(png, dpi=100, metadata={"Software": None})
    if parent_run:
        tracker.log_figure(parent_run, fig, f"{table.name}.png")
        tracker.log_artifact(parent_run, md)
    plt.close(fig)
    return [md, png]


def compose(overrides: list[str]) -> DictConfig:
    """The root config of ``python -m ablate`` with ``overrides``, composed outside a Hydra app."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside the running app (a sweep's end): its own config source
        return hydra_compose("config", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose("config", overrides=overrides)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    named = [a.split("=", 1)[1] for a in args if a.startswith("experiment=")]
    rest = [a for a in args if not a.startswith("experiment=")]
    names = named or ["ablate"] + sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
    written = 0
    for name in names:
        cfg = compose(rest + ([] if name == "ablate" else [f"experiment={name}"]))
        tracker = Tracker.from_config(cfg)
        exp = retry(tracker.client.get_experiment_by_name, cfg.table.name)
        if exp is None:
            if named:
                print(f"error: no runs for experiment '{name}' in {tracker.uri}", file=sys.stderr)
                return 1
            continue
        sweeps = tracker.runs(exp.experiment_id, f"tags.kind = '{KIND_SWEEP}'")
        parent = max(sweeps, key=lambda r: r.info.start_time).info.run_id if sweeps else None
        for path in write_table(cfg, tracker, parent_run=parent):
            print(path)
        written += 1
    if not written:
        print(f"No tables written: no runs in {Tracker.from_config(compose(rest)).uri}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
