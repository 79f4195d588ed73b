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

from collections.abc import Callable
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig

from ablate.store import Tracker
from ablate.tables.collect import collect, loaded_lines, made_lines, resumed_lines, running, state_lines
from ablate.tables.conditions import write_conditions
from ablate.tables.curves import curves_path, from_store, read_curves, write_curves, write_figure
from ablate.tables.forest import write_forest
from ablate.tables.frames import (
    FROM_COUNTS,
    FROM_DETECTIONS,
    detections_from_store,
    read_detections,
    read_frames,
    verdict_metric,
    verdicts_read,
    write_detections,
    write_frames,
)
from ablate.tables.frames import from_store as frames_from_store
from ablate.tables.kept import keep
from ablate.tables.provenance import Recompute, config_of, provenance
from ablate.tables.records import RUNS_DIR, check_records, read_records, records_path, write_records
from ablate.tables.rows import write_rows
from ablate.tables.seal import seal_path
from ablate.tables.spec import COSTS, row_names, table_spec
from ablate.tables.tuning import check_tuned, read_trials, section, write_trials
from ablate.tables.tuning import from_store as trials_from_store
from ablate.tables.tuning import write_figure as write_tuning_figure

LAYOUTS = {"rows": write_rows, "conditions": write_conditions}

__all__ = ["COSTS", "LAYOUTS", "collect", "render_records", "table_spec", "write_table"]


def write_table(
    cfg: DictConfig,
    tracker: Tracker,
    parent_run: str | None = None,
    results_dir: str | Path | None = None,
    fingerprint: Recompute | None = None,
    publish: bool = False,
) -> list[Path]:
    """Write ``cfg``'s table and its figures under ``results_dir`` from the store's runs; log them to
    ``parent_run`` if given. Returns the paths written. ``results_dir`` is required: this package names no folder
    (a sweep's own, or the published one through :func:`ablate.tables.published.publish`). ``fingerprint`` recomputes a run's fingerprint from its
    config (:func:`ablate.jobs.fingerprint.compute`, passed in by the caller) for the provenance footer; without it
    the footer names changed files. ``publish``: write the table's run records first
    (:func:`~ablate.tables.records.write_records`, the curves, counts, detections and trials beside them, and their
    seal, :mod:`~ablate.tables.seal`) and render from them, the one path from runs to a published table."""
    if results_dir is None:
        raise TypeError("write_table() needs results_dir: the folder the table is written into")
    table = table_spec(cfg)
    runs = collect(tracker, table.name)
    written: list[Path] = []
    if publish and len(runs):
        written.append(write_records(runs, str(table.name), results_dir))
        runs = read_records(written[-1])
        written.append(write_curves(from_store(tracker, runs, table), results_dir, str(table.name)))
    decomposes = str(table.primary) in FROM_COUNTS  # a task that keeps counts per test frame (ablate.tables.frames)
    frames = frames_from_store(tracker, runs) if len(runs) and decomposes else pd.DataFrame()
    if publish and (kept := write_frames(frames, results_dir, str(table.name))) is not None:
        written.append(kept)
    keep(runs, "frames", frames)  # the counts per test frame the verdicts read (ablate.tables.twolevel)
    matched = str(table.primary) in FROM_DETECTIONS  # an AP task that keeps its detections per test frame
    detections = detections_from_store(tracker, runs) if len(runs) and matched else pd.DataFrame()
    detections = verdicts_read(detections, *verdict_metric(table))
    if publish and (kept := write_detections(detections, results_dir, str(table.name))) is not None:
        written.append(kept)
    keep(runs, "detections", detections)
    keep(runs, "frames_terms", {})  # the frames' term built from them, once (ablate.tables.columns.table_frames)
    trials = trials_from_store(tracker, str(table.name))
    if publish and (kept := write_trials(trials, results_dir, str(table.name))) is not None:
        written.append(kept)
    keep(runs, "trials", trials)  # what the tuning phase spent (ablate.tables.cost)
    runs_dir = Path(results_dir) / RUNS_DIR
    if publish and any(p.parent == runs_dir for p in written):  # each records file sealed by its writer
        written.append(seal_path(runs_dir, str(table.name)))
    config = lambda run_id: config_of(tracker, run_id)  # noqa: E731
    footer = footer_lines(runs, fingerprint, config, running(tracker, table.name))
    written += render(cfg, table, runs, results_dir, footer, tracker, parent_run, tuning_section(trials, table))
    written += tuning_figure(trials, table, results_dir)
    return written + curves_figure(table, results_dir, tracker, parent_run)


def render_records(
    cfg: DictConfig,
    results_dir: str | Path,
    fingerprint: Recompute | None = None,
    config: Callable[[pd.DataFrame], Callable[[str], DictConfig]] | None = None,
) -> list[Path] | None:
    """Write ``cfg``'s table and its figures under ``results_dir`` from its run records
    (:func:`~ablate.tables.records.records_path`) alone, with no store; None where the table has no records.
    ``config(runs)`` gives the function that composes a recorded run's config today, for the provenance footer.
    Records that are not what was written (:func:`~ablate.tables.records.check_records`: cut short, reordered, a
    line repeated or edited, a column lost) raise :class:`~ablate.tables.seal.BrokenRecords` before anything is
    written."""
    table = table_spec(cfg)
    check_records(results_dir, str(table.name))  # a records file lost beside its curves is broken, not absent
    path = records_path(results_dir, str(table.name))
    if not path.exists():
        return None
    runs = read_records(path)
    keep(runs, "frames", read_frames(results_dir, str(table.name)))
    keep(runs, "detections", read_detections(results_dir, str(table.name)))
    keep(runs, "frames_terms", {})
    trials = read_trials(results_dir, str(table.name))
    keep(runs, "trials", trials)  # what the tuning phase spent (ablate.tables.cost)
    footer = footer_lines(runs, fingerprint, config(runs) if config is not None else None, 0)
    written = render(cfg, table, runs, results_dir, footer, None, None, tuning_section(trials, table))
    written += tuning_figure(trials, table, results_dir)
    return written + curves_figure(table, results_dir, None, None)


def tuning_section(trials: pd.DataFrame, table: DictConfig) -> list[str]:
    """The footer's lines on the table's tuning phase (:mod:`ablate.tables.tuning`); none without trials."""
    return section(trials, table, row_names(table))


def tuning_figure(trials: pd.DataFrame, table: DictConfig, results_dir: str | Path) -> list[Path]:
    """``<table>_tuning.png`` where the table has trials."""
    Path(results_dir).mkdir(parents=True, exist_ok=True)
    path = write_tuning_figure(trials, table, row_names(table), Path(results_dir))
    return [path] if path is not None else []


def curves_figure(
    table: DictConfig, results_dir: str | Path, tracker: Tracker | None, parent_run: str | None
) -> list[Path]:
    """The table's learning curves (:mod:`~ablate.tables.curves`) from the curves kept beside its records, where it
    has them; logged to ``parent_run`` if given."""
    path = curves_path(results_dir, str(table.name))
    figure = write_figure(read_curves(path), table, Path(results_dir)) if path.exists() else None
    if figure is None:
        return []
    if parent_run and tracker is not None:
        tracker.log_artifact(parent_run, figure)
    return [figure]


def footer_lines(
    runs: pd.DataFrame, fingerprint: Recompute | None, config: Callable[[str], DictConfig] | None, in_progress: int
) -> list[str]:
    """The footer under a table: how its rows were made, its provenance, and what it leaves out."""
    return (
        made_lines(runs)
        + resumed_lines(runs)
        + loaded_lines(runs)
        + provenance(runs, fingerprint, config)
        + state_lines(runs, in_progress)
    )


def render(
    cfg: DictConfig,
    table: DictConfig,
    runs: pd.DataFrame,
    results_dir: str | Path,
    footer: list[str],
    tracker: Tracker | None,
    parent_run: str | None,
    after: list[str] | None = None,
) -> list[Path]:
    """The table in its layout (``table.layout``) from its runs; ``after``: markdown lines put under the table's
    footer (its tuning phase, :mod:`ablate.tables.tuning`)."""
    check_tuned(runs)  # one row's seeds are seeds of one config
    layout = table.get("layout", "rows")
    if layout not in LAYOUTS:
        raise ValueError(f"table.layout: {layout!r} is not one of {', '.join(LAYOUTS)}")
    written = LAYOUTS[layout](cfg, table, runs, tracker, parent_run, results_dir, footer)
    if after:
        md = Path(results_dir) / f"{table.name}.md"
        md.write_text(md.read_text().rstrip("\n") + "\n" + "\n".join(after) + "\n")
    forest = write_forest(table, runs, results_dir)  # the race's verdicts at a glance
    if forest is not None and parent_run and tracker is not None:
        tracker.log_artifact(parent_run, forest)
    return written + ([forest] if forest is not None else [])
