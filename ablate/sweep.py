"""A Hydra callback that turns a multirun into one MLflow parent run, and regenerates its table at the end.

Jobs find the parent through a file in the sweep directory (``.parent_run``), which works for the basic launcher
and for ``hydra/launcher=joblib`` alike. A job that fails leaves a note in ``<sweep dir>/failures/``; the callback
lists those notes at the end, marks the parent FAILED and exits with status 1 after the other jobs have run.
"""
from __future__ import annotations

import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from ablate.tracking import KIND_SWEEP, Tracker, git_commit

log = logging.getLogger(__name__)
PARENT_FILE = ".parent_run"
SWEPT_FILE = ".swept_keys"
FAILURES = "failures"


def sweep_dir() -> Path | None:
    """The sweep directory of the running multirun job, or None for a single run."""
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    if hc.mode is None or hc.mode.name != "MULTIRUN":
        return None
    return Path(hc.sweep.dir)


def parent_run_id() -> str | None:
    """The MLflow parent run of the running multirun job, if any."""
    sdir = sweep_dir()
    path = sdir / PARENT_FILE if sdir else None
    return path.read_text().strip() if path and path.exists() else None


def swept_keys() -> list[str] | None:
    """The config keys the running multirun sweeps over (``fusion`` in ``fusion=sum,max``), or None."""
    sdir = sweep_dir()
    path = sdir / SWEPT_FILE if sdir else None
    return path.read_text().split() if path and path.exists() else None


def record_failure(job: str, message: str) -> None:
    """Leave a note that ``job`` failed, for the end-of-sweep summary."""
    sdir = sweep_dir()
    if sdir is not None:
        (sdir / FAILURES).mkdir(parents=True, exist_ok=True)
        (sdir / FAILURES / f"{job}.txt").write_text(message)


def close_dead_sweeps(tracker: Tracker, experiment_id: str) -> int:
    """Mark RUNNING sweep runs of this host whose process is gone (a killed multirun) as KILLED."""
    closed = 0
    for run in tracker.runs(experiment_id, f"tags.kind = '{KIND_SWEEP}' and attributes.status = 'RUNNING'"):
        tags = run.data.tags
        if tags.get("host") == socket.gethostname() and tags.get("pid", "").isdigit() and not _alive(int(tags["pid"])):
            tracker.end(run.info.run_id, "KILLED")
            closed += 1
    return closed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def fixed_overrides(config: DictConfig) -> list[str]:
    """The sweep's command-line overrides that are not swept (``experiment=...``, ``scale=smoke``): with a row
    and a seed added, they compose that job's config again."""
    parsed = OverridesParser.create().parse_overrides(list(config.hydra.overrides.task))
    return [o.input_line for o in parsed if not o.is_sweep_override()]


class SweepCallback(Callback):
    """Creates the parent run before the jobs, and closes it, writes the table and reports failures after."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        sdir = Path(str(config.hydra.sweep.dir))
        sdir.mkdir(parents=True, exist_ok=True)
        tracker = Tracker.from_config(config)
        exp = tracker.experiment_id(config.table.name)
        close_dead_sweeps(tracker, exp)
        overrides = " ".join(config.hydra.overrides.task)
        run_id = tracker.start(exp, f"sweep {time.strftime('%Y-%m-%d %H:%M:%S')}", {
            "kind": KIND_SWEEP, "table": config.table.name, "overrides": overrides, "git_commit": git_commit(),
            "sweep_dir": str(sdir), "host": socket.gethostname(), "pid": str(os.getpid())})
        (sdir / PARENT_FILE).write_text(run_id)
        parsed = OverridesParser.create().parse_overrides(list(config.hydra.overrides.task))
        (sdir / SWEPT_FILE).write_text(" ".join(o.get_key_element() for o in parsed if o.is_sweep_override()))
        log.info("MLflow parent run %s in experiment '%s' (%s)", run_id, config.table.name, tracker.uri)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from ablate.report import write_table

        sdir = Path(str(config.hydra.sweep.dir))
        tracker = Tracker.from_config(config)
        parent = (sdir / PARENT_FILE).read_text().strip() if (sdir / PARENT_FILE).exists() else None
        failures = sorted((sdir / FAILURES).glob("*.txt")) if (sdir / FAILURES).is_dir() else []
        if config.get("comp_time", {}).get("after_sweep") and config.table.rows:
            from ablate.latency import measure
            from ablate.report import compose

            try:
                measure(config, tracker, compose, fixed_overrides(config), only_if_missing=True)
            except Exception as err:  # the table is written all the same, its latency column empty
                log.error("Could not time the rows side by side (python -m ablate.latency): %s", err)
        try:
            paths = write_table(config, tracker, parent_run=parent)
            log.info("Table written: %s", ", ".join(str(p) for p in paths))
        except Exception as err:  # a table that cannot be written must not hide the jobs' own outcome
            log.error("Could not write the table '%s': %s", config.table.name, err)
            failures.append(Path("report"))
        if parent:
            tracker.end(parent, "FAILED" if failures else "FINISHED")
        if failures:
            log.error("%d job(s) failed:", len(failures))
            for path in failures:
                note = path.read_text().strip().splitlines() if path.exists() else ["the table could not be written"]
                log.error("  %s: %s", path.stem, note[-1] if note else "")
            raise SystemExit(1)
