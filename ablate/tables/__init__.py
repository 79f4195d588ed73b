"""Tables from runs: the store's runs -> pandas -> ``results/<table>.md`` and ``results/<table>.png``.

Only FINISHED job runs count (per row and seed the latest, at the scale of the latest run), so a failed job never
becomes a row; a row with no finished run is listed under the table instead, and the footer counts the runs still
RUNNING (a report while a sweep writes) and the bad frames the runs skipped. The same runs give the same bytes:
no timestamps, rows in the paper's order, PNG written without metadata. It imports the store, never the job or the
sweep (:mod:`ablate.jobs`, :mod:`ablate.sweep`): what it needs from them (recomputing a run's fingerprint) is passed in.

Two layouts (``table.layout``) share one API, ``write_<layout>(cfg, table, runs, tracker, parent_run,
results_dir, footer) -> paths``: ``rows`` (:mod:`~ablate.tables.rows`, the default) has a row per trained model;
``conditions`` (:mod:`~ablate.tables.conditions`, DGFN Table I's shape) has a row per test condition and columns
model x metric, from runs tested under ``task.eval_conditions``.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from ablate.store import Tracker
from ablate.tables.collect import collect, made_lines, running, state_lines
from ablate.tables.conditions import write_conditions
from ablate.tables.provenance import Recompute, config_of, provenance
from ablate.tables.rows import write_rows
from ablate.tables.spec import COSTS, table_spec

LAYOUTS = {"rows": write_rows, "conditions": write_conditions}

__all__ = ["COSTS", "LAYOUTS", "collect", "table_spec", "write_table"]


def write_table(
    cfg: DictConfig,
    tracker: Tracker,
    parent_run: str | None = None,
    results_dir: str | Path = "results",
    fingerprint: Recompute | None = None,
) -> list[Path]:
    """Write ``cfg``'s table and its figures under ``results_dir`` from the store's runs; log them to
    ``parent_run`` if given. Returns the paths written. ``fingerprint`` recomputes a run's fingerprint from its
    config (:func:`ablate.jobs.fingerprint.compute`, passed in by the caller) for the provenance footer; without it
    the footer names changed files."""
    table = table_spec(cfg)
    layout = table.get("layout", "rows")
    if layout not in LAYOUTS:
        raise ValueError(f"table.layout: {layout!r} is not one of {', '.join(LAYOUTS)}")
    runs = collect(tracker, table.name)
    footer = made_lines(runs) + provenance(runs, fingerprint, lambda run_id: config_of(tracker, run_id))
    footer += state_lines(runs, running(tracker, table.name))
    return LAYOUTS[layout](cfg, table, runs, tracker, parent_run, results_dir, footer)
