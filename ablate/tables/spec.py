"""A table's spec: ``cfg.table`` (conf/experiment/<table>.yaml) with the task's metrics where it leaves them null."""

from __future__ import annotations

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
