"""A table's spec: ``cfg.table`` (conf/experiment/<table>.yaml) with the task's metrics where it leaves them null."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

from omegaconf import DictConfig, OmegaConf

#: Cost columns every table gets after its metrics (from ``python -m ablate.latency``, which a multirun runs at its
#: end); a table may list one itself to give it its paper's label and numbers (ChiNet's "Comp Time (ms)").
COSTS = {"latency_ms": "Latency (ms)", "params_m": "Params (M)", "macs_g": "MACs (G)"}


LOWER_IS_BETTER = {"comp_time_ms", *COSTS}


def table_spec(cfg: DictConfig) -> DictConfig:
    """``cfg.table`` with ``metrics`` and ``primary`` falling back to the task's when the table leaves them null."""
    table = cast(dict[str, Any], OmegaConf.to_container(cfg.table, resolve=True))
    table["metrics"] = table.get("metrics") or OmegaConf.to_container(cfg.get("metrics") or {}, resolve=True)
    table["primary"] = table.get("primary") or cfg.get("primary") or next(iter(table["metrics"]), None)
    table["metrics"] = {**table["metrics"], **{k: v for k, v in COSTS.items() if k not in table["metrics"]}}
    return cast(DictConfig, OmegaConf.create(table))


def run_rows(table: DictConfig) -> list[str]:
    """The rows a table runs, in its order: its ``table.rows`` but those it only quotes from the paper
    (``paper_only``). An experiment lists its rows once, there; the racing sweeper sweeps ``row`` over these."""
    return [str(r["row"]) for r in table.get("rows") or [] if not r.get("paper_only")]


def sweep_params(params: Mapping[str, Any], arguments: Sequence[str], table: DictConfig) -> dict[str, Any]:
    """A sweeper's ``params`` with ``row`` swept over the rows the table runs (:func:`run_rows`), unless ``params``
    or the command line's ``arguments`` name ``row`` already; an ad-hoc sweep has no rows, and nothing is added. The
    racing sweeper launches these, and a sweep's progress plans with them."""
    named = {a.split("=", 1)[0].lstrip("+~") for a in arguments} | set(params)
    rows = run_rows(table)
    return {**params, "row": ",".join(rows)} if rows and "row" not in named else dict(params)


def row_names(table: DictConfig) -> dict[str, str]:
    """Each row of ``table`` and the name its table shows."""
    return {str(r.row): str(r.get("name", r.row)) for r in table.rows}
