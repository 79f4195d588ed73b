"""A sweep's end, once its last job has run: the rows timed side by side, its table written (and published where
``publish=true``), its parent run closed, and its failed jobs listed.

A job that fails leaves a note in ``<sweep dir>/failures/`` (:meth:`ablate.store.SweepContext.record_failure`); the
end lists those notes, marks the parent FAILED and exits with status 1. A table that cannot be written fails the
sweep the same way, after the parent run is closed: it never hides the jobs' own outcome.
"""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path

from omegaconf import DictConfig

from ablate.analysis.compare import against_published
from ablate.analysis.latency import measure
from ablate.config import composer
from ablate.jobs import fingerprint
from ablate.store import AccessDenied, ServerUnreachable, Tracker, is_server
from ablate.sweep.parent import STORE_ERRORS, fixed_overrides, sweep_context
from ablate.tables import COSTS, published, table_spec, write_table
from ablate.tables.records import read_records, records_path

log = logging.getLogger(__name__)


def publish(paths: list[Path], source: Path, results: Path, config: DictConfig) -> list[Path]:
    """Copy a sweep's table, its records and its figures (``paths``, under ``source``) to ``results`` (``publish=true``),
    and rewrite the results summary there and in the README beside it (:func:`ablate.tables.published.summary`); the
    copies."""
    copies = published.copy_in(paths, source, results)
    fixed = [o for o in fixed_overrides(config) if not o.startswith("experiment=")]
    specs = [table_spec(composer(config)([*fixed, f"experiment={name}"])) for name in published.with_tables(results)]
    return copies + published.summary(specs)  # the driver runs in the launch directory


def beside_published(config: DictConfig, sweep_dir: Path, results: Path) -> None:
    """Log the sweep's rows beside the published records of its table (:mod:`ablate.analysis.compare`), and keep the
    comparison as ``<table>_vs_published.md`` in the sweep's folder."""
    table = table_spec(config)
    mine = records_path(sweep_dir, str(table.name))
    text = against_published(read_records(mine), table, results) if mine.exists() else None
    if text is None:
        log.info("No published records of %s to compare with (%s)", table.name, records_path(results, table.name))
        return
    (sweep_dir / f"{table.name}_vs_published.md").write_text(text)
    log.info("Your rows beside the published ones:\n%s", text)


#: What an MLflow metric name may not hold.
NOT_IN_A_NAME = re.compile(r"[^\w\-. :/]")


def row_means(tracker: Tracker, parent: str, config: DictConfig, records: Path) -> None:
    """Each row's mean of the table's primary metric as a metric of the sweep's run (``<metric>/<row>``), so that
    its collapsed row in the MLflow UI shows the table's outcome."""
    table = table_spec(config)
    if not records.exists() or not table.primary:
        return
    runs = read_records(records)
    if str(table.primary) not in runs:
        return
    means = runs.groupby("row")[str(table.primary)].mean().dropna()
    named = {f"{table.primary}/{NOT_IN_A_NAME.sub(':', str(row))}": float(v) for row, v in means.items()}
    tracker.log_metrics(parent, named)  # MLflow's names take no `=`: `model=unet` is `model:unet`


def time_rows(config: DictConfig, tracker: Tracker) -> None:
    """Time the table's rows side by side (``comp_time.after_sweep``, :mod:`ablate.analysis.latency`), those not
    timed yet; the table is written all the same where they cannot be."""
    if not (config.get("comp_time", {}).get("after_sweep") and config.table.rows):
        return
    try:
        measure(config, tracker, composer(config), fixed_overrides(config), only_if_missing=True)
    except Exception as err:  # builds and runs every row's network: whatever fails, the table keeps its other columns
        log.error("Could not time the rows side by side (python -m ablate.latency): %s", err)


def write(config: DictConfig, tracker: Tracker, parent: str | None, sweep_dir: Path, launch_dir: Path) -> bool:
    """Write the sweep's table into its folder, its rows' means on its parent run, and publish it (``publish=true``)
    or set it beside the published one; False where the table could not be written."""
    try:
        paths = write_table(config, tracker, parent, sweep_dir, fingerprint.compute, publish=True)
        log.info("Table written: %s", ", ".join(str(p) for p in paths))
        if parent:
            try:
                row_means(tracker, parent, config, records_path(sweep_dir, str(config.table.name)))
            except (*STORE_ERRORS, KeyError, ValueError) as err:  # a convenience: never the reason a sweep fails
                log.warning("Could not log the rows' means on the sweep's run: %s", err)
        if config.get("publish"):
            copies = publish(paths, sweep_dir, launch_dir / published.RESULTS, config)
            log.info("Published: %s", ", ".join(str(p) for p in copies))
        elif config.table.rows:
            beside_published(config, sweep_dir, launch_dir / published.RESULTS)
    except Exception as err:  # renders every run the store holds: whatever fails, the jobs' own outcome is reported
        log.error("Could not write the table '%s': %s", config.table.name, err)
        return False
    return True


def close_parent(config: DictConfig, tracker: Tracker, parent: str, failed: bool) -> None:
    """End the sweep's parent run, and log the link to the table's runs in the MLflow UI."""
    tracker.end(parent, "FAILED" if failed else "FINISHED")
    try:
        spec = table_spec(config)
        cond = spec.get("primary_condition")  # a rows table read under one test condition
        metrics = [f"{cond}/{m}" if cond and m not in COSTS else m for m in spec.metrics]
        link = tracker.share_table_view(tracker.experiment_id(config.table.name), metrics)
        where = "" if is_server(tracker.uri) else f" (`mlflow ui` in {config.hydra.runtime.cwd})"
        log.info("Runs in the MLflow UI%s: %s", where, link)
    except STORE_ERRORS as err:  # a convenience: never the reason a sweep fails
        log.warning("Could not store the MLflow UI view of the table: %s", err)


def finish(config: DictConfig) -> None:
    """Time the rows, write the table, close the parent run and list the failures (status 1 where a job failed or
    the table could not be written); a store that does not answer (past ``logger.outage_s``) or refuses this client
    is one line and status 1."""
    context = sweep_context(config)
    assert context.sweep_dir is not None
    try:
        tracker = Tracker.from_config(config, context)
        time_rows(config, tracker)
        failures = context.failures()
        if not write(config, tracker, context.parent_run, context.sweep_dir, context.launch_dir):
            failures.append(Path("report"))
        if context.parent_run:
            close_parent(config, tracker, context.parent_run, bool(failures))
    except (ServerUnreachable, AccessDenied) as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    if failures:
        log.error("%d job(s) failed:", len(failures))
        for path in failures:
            log.error("  %s: %s", path.stem, note_line(path.read_text() if path.exists() else ""))
        raise SystemExit(1)


def note_line(note: str, width: int = 400) -> str:
    """A failed job's note as one line of the closing summary: its lines joined (an error that names what failed
    on one line and where on the next, as Hydra's instantiation errors do: ``Error locating target 'my_ops.Product'``,
    then ``full_key: model.fusion``), cut at ``width`` characters; an empty note is the table's."""
    lines = [line.strip() for line in note.strip().splitlines() if line.strip()]
    text = "; ".join(lines) or "the table could not be written"
    return text if len(text) <= width else text[: width - 1] + "…"
