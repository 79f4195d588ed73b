"""A Hydra callback that turns a multirun into one MLflow parent run, and regenerates its table at the end.

It records the sweep's store, parent run and swept keys in the sweep directory, where every job finds them
(:class:`ablate.store.SweepContext`). A job that fails leaves a note in ``<sweep dir>/failures/``; the
callback lists those notes at the end, marks the parent FAILED and exits with status 1 after the other jobs have run.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import re
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from ablate.analysis.compare import against_published
from ablate.analysis.latency import measure
from ablate.config import CONF, composer
from ablate.jobs import fingerprint, stage1
from ablate.jobs.preempt import GRACE_S, alive, install_parent
from ablate.store import (
    KIND_SWEEP,
    AccessDenied,
    ServerUnreachable,
    SweepContext,
    Tracker,
    config_hash,
    is_server,
    provenance_tags,
)
from ablate.store.context import PARENT_FILE, STORE_FILE, SWEPT_FILE
from ablate.sweep import progress
from ablate.tables import COSTS, table_spec, write_table
from ablate.tables.index import write_index
from ablate.tables.records import read_records, records_path

log = logging.getLogger(__name__)


def close_dead_sweeps(tracker: Tracker, experiment_id: str) -> int:
    """Mark RUNNING sweep runs of this host whose process is gone (a killed multirun) as KILLED."""
    closed = 0
    for run in tracker.runs(experiment_id, f"tags.kind = '{KIND_SWEEP}' and attributes.status = 'RUNNING'"):
        tags = run.data.tags
        if tags.get("host") == socket.gethostname() and tags.get("pid", "").isdigit() and not alive(int(tags["pid"])):
            tracker.end(run.info.run_id, "KILLED")
            closed += 1
    return closed


def stop_sweep(tracker: Tracker, run_id: str, signame: str, stopped: int, killed: int) -> None:
    """Record a sweep stopped by ``signame`` (its workers already stopped, :func:`ablate.jobs.preempt.stop_workers`):
    its parent run KILLED with the reason, and one line for the user."""
    reason = f"stopped by {signame}: {stopped} worker(s) stopped" + (
        f", {killed} killed after {GRACE_S:.0f} s" if killed else ", each job checkpointed and marked KILLED"
    )
    try:
        tracker.set_tags(run_id, {"killed_by": signame, "kill_reason": reason})
        tracker.end(run_id, "KILLED")
    except Exception as err:
        log.error("Could not mark the sweep's run %s KILLED: %s", run_id, err)
    print(f"stopped: sweep {reason}; the same command again resumes its jobs", file=sys.stderr)


#: The extra of pyproject.toml that installs a launcher plugin, by the plugin's package.
LAUNCHER_EXTRAS = {"hydra_plugins.hydra_ray_launcher": "ray", "hydra_plugins.hydra_submitit_launcher": "slurm"}


def check_launcher(config: DictConfig) -> None:
    """Fail with one line naming the launcher and its extra when its plugin is not installed (Hydra would otherwise
    fail later, on the unresolvable ``_target_``)."""
    target = str(OmegaConf.select(config, "hydra.launcher._target_", default="") or "")
    package = ".".join(target.split(".")[:2])
    if package.startswith("hydra_plugins.") and importlib.util.find_spec(package) is None:
        choice = OmegaConf.select(config, "hydra.runtime.choices", default={}).get("hydra/launcher", target)
        extra = LAUNCHER_EXTRAS.get(package)
        hint = f"pip install -e '.[{extra}]'" if extra else f"install the package that provides {package}"
        raise ValueError(f"hydra/launcher={choice} needs {package}, which is not installed: {hint}")


def ray_driver_auth(config: DictConfig) -> bool:
    """Let the driver of a ``hydra/launcher=ray`` sweep authenticate to a running Ray cluster; True if it now does.

    Workaround. Ray (>= 2.52) checks a token on every connection once the cluster has token authentication on,
    and ``ray start --head`` turns it on by itself when a token is available (``RAY_AUTH_TOKEN``,
    ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``) and ``RAY_AUTH_MODE`` is unset; ``ray.init(address=...)``,
    which hydra-ray-launcher calls in the driver, does not, so the driver connects without the token and is
    refused. Before the launcher starts, this applies to the driver the very check ``ray start`` applies
    (``maybe_enable_token_auth_if_token_available``, ray/scripts/scripts.py), which sets ``RAY_AUTH_MODE=token``
    when a token is there; an explicit ``RAY_AUTH_MODE`` is respected. Docs:
    https://docs.ray.io/en/latest/ray-security/token-auth.html
    """
    target = str(OmegaConf.select(config, "hydra.launcher._target_", default="") or "")
    if not target.startswith("hydra_plugins.hydra_ray_launcher") or not OmegaConf.select(
        config, "hydra.launcher.ray.init.address", default=None
    ):
        return False
    try:
        from ray._private.authentication.authentication_token_setup import (
            maybe_enable_token_auth_if_token_available,
        )
    except ImportError:  # a Ray without token authentication (< 2.52)
        return False
    enabled = maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
    if enabled:
        log.info("Ray: connecting with the cluster's token (RAY_AUTH_MODE=token)")
    return enabled


def fixed_overrides(config: DictConfig) -> list[str]:
    """The sweep's command-line overrides that are not swept (``experiment=...``, ``scale=smoke``): with a row
    and a seed added, they compose that job's config again."""
    parsed = OverridesParser.create().parse_overrides(list(config.hydra.overrides.task))
    return [str(o.input_line) for o in parsed if not o.is_sweep_override()]


#: Where published tables live, under the launch directory; a sweep writes its own table into its sweep folder.
RESULTS = "results"


def publish(paths: list[Path], source: Path, results: Path, config: DictConfig) -> list[Path]:
    """Copy a sweep's table, its records and its figures (``paths``, under ``source``) to ``results`` (``publish=true``),
    and rewrite the results summary there and in the README beside it (:mod:`ablate.tables.index`); the copies."""
    copies = []
    for path in paths:
        target = results / path.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
        copies.append(target)
    experiments = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
    fixed = [o for o in fixed_overrides(config) if not o.startswith("experiment=")]
    specs = [table_spec(composer(config)([*fixed, f"experiment={name}"])) for name in experiments]
    return copies + write_index(specs, RESULTS, "README.md")  # the driver runs in the launch directory


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


def parent_name(config: DictConfig) -> str:
    """The sweep's run name in the MLflow UI: its table, its scale and the overrides it was launched with."""
    overrides = [o for o in fixed_overrides(config) if not o.startswith(("experiment=", "scale="))]
    swept = [o for o in config.hydra.overrides.task if o not in fixed_overrides(config)]
    return " ".join([str(config.table.name), f"scale={config.scale.name}", *overrides, *swept])


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


def sweep_context(config: DictConfig) -> SweepContext:
    """The sweep's context, read where the driver's callback starts: its launch and sweep directories from the
    multirun's config, and what the sweep directory's files hold by now."""
    launch = Path(str(config.hydra.runtime.cwd))
    return SweepContext.of_sweep(launch / str(config.hydra.sweep.dir), launch)


class SweepCallback(Callback):
    """Creates the parent run before the jobs, and closes it, writes the table and reports failures after."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Check the launcher and the store, then open the parent run. A sweep that cannot be set up stops here
        with one line: Hydra would only warn about an exception from a callback and launch the jobs anyway."""
        try:
            self._start(config)
        except Exception as err:
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None

    def _start(self, config: DictConfig) -> None:
        context = sweep_context(config)
        sdir = context.sweep_dir
        assert sdir is not None
        check_launcher(config)
        sdir.mkdir(parents=True, exist_ok=True)
        ray_driver_auth(config)
        tracker = Tracker.from_config(config, context)
        context.record(STORE_FILE, json.dumps({"uri": tracker.uri, "artifact_location": tracker.artifact_location}))
        exp = tracker.experiment_id(config.table.name)
        close_dead_sweeps(tracker, exp)
        overrides = " ".join(config.hydra.overrides.task)
        run_id = tracker.start(
            exp,
            parent_name(config),
            {
                "kind": KIND_SWEEP,
                "table": config.table.name,
                "overrides": overrides,
                **provenance_tags(context.launch_dir),
                "sweep_dir": str(sdir),
                "host": socket.gethostname(),
                "pid": str(os.getpid()),
            },
        )
        context.record(PARENT_FILE, run_id)
        if "joblib" in str(OmegaConf.select(config, "hydra.launcher._target_", default="")):
            install_parent(lambda name, stopped, killed: stop_sweep(tracker, run_id, name, stopped, killed))
        parsed = OverridesParser.create().parse_overrides(list(config.hydra.overrides.task))
        # the command line's swept keys; the racing sweeper records its own over them, its params included
        context.record(SWEPT_FILE, " ".join(o.get_key_element() for o in parsed if o.is_sweep_override()))
        log.info("MLflow parent run %s in experiment '%s' (%s)", run_id, config.table.name, tracker.uri)
        planned = progress.start(sdir, config)
        try:
            from ablate.jobs.job import done_in_store
            from ablate.jobs.spec import job_kind
            from ablate.sweep.plan import expert_seconds, kind_seconds, log_plan, row_jobs  # torch, Lightning
            from ablate.tables.tuning import trial_objectives

            # a resumed tuning phase: its stage-2 trials and raced jobs as the sweeper will launch them
            objectives = trial_objectives(tracker, str(config.table.name)) if config.table.get("tune") else None
            plan = log_plan(
                config,
                progress.workers(config),
                lambda cfg: done_in_store(tracker, exp, config_hash(cfg), job_kind(cfg)),
                objectives,
            )
            progress.estimated(sdir, kind_seconds(plan), row_jobs(plan))
            progress.experts_planned(sdir, *expert_seconds(plan))
        except Exception as err:  # the plan is a convenience: never the reason a sweep does not start
            log.warning("Could not plan the sweep: %s", err)
            log.info("Sweep of %d job(s), %s at a time", planned, progress.workers(config))

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._job_started = time.monotonic()
        stage1.CURRENT.clear()

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        """Count the job in the sweep's progress and log the sweep's progress line with its ETA."""
        sdir = SweepContext.current().sweep_dir
        if sdir is None or not hasattr(self, "_job_started"):
            return
        status = job_return._return_value if job_return.status.name == "COMPLETED" else "FAILED"
        try:
            overrides, seconds = list(config.hydra.overrides.task), time.monotonic() - self._job_started
            row, trial = progress.job_row(overrides), progress.job_trial(overrides)
            kind = progress.job_kind(overrides)
            ran = stage1.CURRENT  # what the job spent on its experts (ablate.jobs.stage1)
            line = progress.finished(
                sdir, str(status), seconds, progress.workers(config), kind, row, trial, list(ran.trained), ran.seconds
            )
            log.info(line)
        except Exception as err:  # progress is a convenience: never the reason a job fails
            log.warning("Could not record the sweep's progress: %s", err)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Time the rows, write the table, close the parent run and list the failures; a store that does not
        answer (past ``logger.outage_s``) or refuses this client is one line and status 1."""
        try:
            self._end(config)
        except (ServerUnreachable, AccessDenied) as err:
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(1) from None

    def _end(self, config: DictConfig) -> None:
        context = sweep_context(config)
        tracker = Tracker.from_config(config, context)
        parent = context.parent_run
        failures = context.failures()
        if config.get("comp_time", {}).get("after_sweep") and config.table.rows:
            try:
                measure(config, tracker, composer(config), fixed_overrides(config), only_if_missing=True)
            except Exception as err:  # the table is written all the same, its latency column empty
                log.error("Could not time the rows side by side (python -m ablate.latency): %s", err)
        try:
            assert context.sweep_dir is not None
            paths = write_table(config, tracker, parent, context.sweep_dir, fingerprint.compute, publish=True)
            log.info("Table written: %s", ", ".join(str(p) for p in paths))
            if parent:
                try:
                    row_means(tracker, parent, config, records_path(context.sweep_dir, str(config.table.name)))
                except Exception as err:  # a convenience: never the reason a sweep fails
                    log.warning("Could not log the rows' means on the sweep's run: %s", err)
            if config.get("publish"):
                published = publish(paths, context.sweep_dir, context.launch_dir / RESULTS, config)
                log.info("Published: %s", ", ".join(str(p) for p in published))
            elif config.table.rows:
                beside_published(config, context.sweep_dir, context.launch_dir / RESULTS)
        except Exception as err:  # a table that cannot be written must not hide the jobs' own outcome
            log.error("Could not write the table '%s': %s", config.table.name, err)
            failures.append(Path("report"))
        if parent:
            tracker.end(parent, "FAILED" if failures else "FINISHED")
            try:
                spec = table_spec(config)
                cond = spec.get("primary_condition")  # a rows table read under one test condition
                metrics = [f"{cond}/{m}" if cond and m not in COSTS else m for m in spec.metrics]
                link = tracker.share_table_view(tracker.experiment_id(config.table.name), metrics)
                where = "" if is_server(tracker.uri) else f" (`mlflow ui` in {config.hydra.runtime.cwd})"
                log.info("Runs in the MLflow UI%s: %s", where, link)
            except Exception as err:  # a convenience: never the reason a sweep fails
                log.warning("Could not store the MLflow UI view of the table: %s", err)
        if failures:
            log.error("%d job(s) failed:", len(failures))
            for path in failures:
                note = path.read_text().strip().splitlines() if path.exists() else ["the table could not be written"]
                log.error("  %s: %s", path.stem, note[-1] if note else "")
            raise SystemExit(1)
