"""A sweep's start: its launcher checked, its parent run opened in the store, and where its jobs find both.

The racing sweeper (``hydra_plugins/ablate_racing_sweeper``) checks the launcher before Hydra builds it
(:func:`check_launcher`, :func:`ray_driver_auth`), then opens the sweep's MLflow parent run (:func:`open_parent`)
and records the store and the run in the sweep's state file (:mod:`ablate.sweep.state`), where every job finds them
(:class:`ablate.store.SweepContext`). A parent run left RUNNING by a killed sweep of this host is closed KILLED
first (:func:`close_dead_sweeps`); a joblib sweep stopped by a signal closes its own (:func:`stop_sweep`).
"""

from __future__ import annotations

import importlib.util
import logging
import os
import socket
import sys
from pathlib import Path

from hydra.core.override_parser.overrides_parser import OverridesParser
from mlflow.exceptions import MlflowException
from omegaconf import DictConfig, OmegaConf

from ablate.jobs.preempt import GRACE_S, alive, install_parent
from ablate.store import KIND_SWEEP, AccessDenied, ServerUnreachable, SweepContext, Tracker, provenance_tags
from ablate.sweep import state

log = logging.getLogger(__name__)

#: What a call to the store fails as (:func:`ablate.store.retry.retry`): an error of MLflow's, a store that does not
#: answer or refuses this client, a file of a local store that cannot be written.
STORE_ERRORS = (MlflowException, ServerUnreachable, AccessDenied, OSError)


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
    its parent run KILLED with the reason, and one line for the user, whether or not the store took it."""
    reason = f"stopped by {signame}: {stopped} worker(s) stopped" + (
        f", {killed} killed after {GRACE_S:.0f} s" if killed else ", each job checkpointed and marked KILLED"
    )
    try:
        tracker.set_tags(run_id, {"killed_by": signame, "kill_reason": reason})
        tracker.end(run_id, "KILLED")
    except STORE_ERRORS as err:
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


def parent_name(config: DictConfig) -> str:
    """The sweep's run name in the MLflow UI: its table, its scale and the overrides it was launched with."""
    overrides = [o for o in fixed_overrides(config) if not o.startswith(("experiment=", "scale="))]
    swept = [o for o in config.hydra.overrides.task if o not in fixed_overrides(config)]
    return " ".join([str(config.table.name), f"scale={config.scale.name}", *overrides, *swept])


def sweep_context(config: DictConfig) -> SweepContext:
    """The sweep's context in its driver: its launch and sweep directories from the multirun's config, and what the
    sweep's state file holds by now."""
    launch = Path(str(config.hydra.runtime.cwd))
    return SweepContext.of_sweep(launch / str(config.hydra.sweep.dir), launch)


def open_parent(config: DictConfig) -> tuple[Tracker, str]:
    """Open the sweep's parent run (its dead predecessors of this host closed first) and record it and its store in
    the sweep's state file; the store and the run. A joblib sweep stopped by a signal closes it KILLED."""
    context = sweep_context(config)
    sdir = context.sweep_dir
    assert sdir is not None
    sdir.mkdir(parents=True, exist_ok=True)
    tracker = Tracker.from_config(config, context)
    state.record(sdir, store={"uri": tracker.uri, "artifact_location": tracker.artifact_location})
    exp = tracker.experiment_id(config.table.name)
    close_dead_sweeps(tracker, exp)
    tags = {
        "kind": KIND_SWEEP,
        "table": config.table.name,
        "overrides": " ".join(config.hydra.overrides.task),
        **provenance_tags(context.launch_dir),
        "sweep_dir": str(sdir),
        "host": socket.gethostname(),
        "pid": str(os.getpid()),
    }
    run_id = tracker.start(exp, parent_name(config), tags)
    state.record(sdir, parent_run=run_id)
    if "joblib" in str(OmegaConf.select(config, "hydra.launcher._target_", default="")):
        install_parent(lambda name, stopped, killed: stop_sweep(tracker, run_id, name, stopped, killed))
    log.info("MLflow parent run %s in experiment '%s' (%s)", run_id, config.table.name, tracker.uri)
    return tracker, run_id
