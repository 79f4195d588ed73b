"""Per-row summaries of a table's runs (mean, std, n, 95 % CI over seeds, the paper's value), the reference row,
Kendall's τ against the paper's ranking, and the cell formats both layouts share."""

from __future__ import annotations

import numpy as np
import pandas as pd
from omegaconf import DictConfig
from scipy.stats import kendalltau

from ablate.tables.significance import mean_ci
from ablate.tables.spec import LOWER_IS_BETTER


def typed_order(runs: pd.DataFrame) -> list[str]:
    """The rows of an ad-hoc sweep (a table that names none) in the order the command line gave them: by the
    sweep's job number of their runs (Hydra numbers the jobs in the order of the swept values), then by name."""
    if not len(runs):
        return []
    order = runs.groupby("row")["job_num"].min() if "job_num" in runs else runs.groupby("row").size() * 0
    return [str(r) for r, _ in sorted(order.items(), key=lambda item: (item[1], str(item[0])))]


def summarise(runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """Per table row (in the paper's order): mean, std, n and 95 % CI (``ablate.tables.significance.mean_ci``) of each
    metric over seeds, and the paper's value."""
    rows = list(table.rows) or [{"row": r, "name": r, "paper": {}} for r in typed_order(runs)]
    out = []
    for spec in rows:
        sel = runs[runs["row"] == spec["row"]] if len(runs) else runs
        if sel.empty and not spec.get("paper_only"):
            continue
        rec = {
            "row": spec["row"],
            "name": spec.get("name", spec["row"]),
            "n": len(sel),
            **{key: str(spec.get(key, "")) for key in table.get("text_columns") or {}},
        }
        for key in table.metrics:
            values = sel[key].dropna() if key in sel else pd.Series(dtype=float)
            rec[f"{key}_mean"] = values.mean() if len(values) else np.nan
            rec[f"{key}_std"] = values.std(ddof=1) if len(values) > 1 else np.nan
            ci = mean_ci(values)
            rec[f"{key}_lo"], rec[f"{key}_hi"] = ci.lo, ci.hi
            rec[f"{key}_paper"] = (spec.get("paper") or {}).get(key, np.nan)
        out.append(rec)
    return pd.DataFrame.from_records(out)


def fmt(mean: float, std: float, bold: bool) -> str:
    if np.isnan(mean):
        return "—"
    text = f"{mean:.2f}" + ("" if np.isnan(std) else f" ± {std:.2f}")
    return f"**{text}**" if bold else text


def best_of(values: pd.Series, key: str) -> float:
    values = values.dropna()
    if values.empty:
        return np.nan
    return values.min() if key in LOWER_IS_BETTER else values.max()


def bold_of(values: pd.Series, key: str) -> float:
    """The value a table's column bolds: its best (:func:`best_of`), none (NaN) where every row has the same value,
    so that a tie of all rows is not shown as a win."""
    known = pd.Series(values, dtype=float).dropna()
    return np.nan if len(known) > 1 and known.nunique() == 1 else best_of(known, key)


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
    best = best_of(means, table.primary)
    return str(sel["row"][means == best].iloc[0]) if not np.isnan(best) else str(sel["row"].iloc[0])


def per_seed(runs: pd.DataFrame, row: str, key: str) -> pd.Series:
    """The values of ``key`` of ``row``'s runs, by seed (none missing)."""
    if key not in runs or not (mine := runs["row"] == row).any():
        return pd.Series(dtype=float)
    values = runs[key][mine]  # two columns of a wide frame: selecting its rows first takes 50x longer
    return values.set_axis(pd.Index(runs["seed"][mine], name="seed")).dropna()


def signed(x: float) -> str:
    return f"{x:+.2f}".replace("-", "−")
