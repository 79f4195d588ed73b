"""Who made a run and with what: the config hash, the params, the row a job fills, and the code's version.

A run records the version of the ``ablate`` that ran (:func:`code_version`: the installed version and, where its
source is a git checkout, that checkout's commit with ``-dirty``), and apart from it the launch directory's own
commit where the launch directory is a checkout (:func:`git_commit`). A sweep launched from a folder that is not a
git repository, with ``ablate`` installed from a checkout, so still records the commit of the code that ran.
"""

from __future__ import annotations

import getpass
import hashlib
import json
import os
import subprocess
from collections.abc import Iterable
from functools import lru_cache
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from ablate import __version__, hardware

#: The checkout ``ablate`` is imported from, when it is one (an editable install or a clone on ``sys.path``).
SOURCE = Path(__file__).resolve().parents[2]

#: Config keys that do not change a result, so they are left out of the config hash (``table`` holds only
#: the paper's numbers and row names; the experiment a run lands in already separates tables; the float32 feature
#: cache of frozen experts, ablate.jobs.experts.FeatureCache, changes the speed only).
UNHASHED = (
    "force",
    "publish",
    "plan",
    "trace",
    "tuned",
    "logger",
    "hydra",
    "table",
    "scale.race",
    "trainer.enable_progress_bar",
    "data.num_workers",
    "data.memo_gb",
    "experts.cache_features",
    "experts.cache_max_gb",
    "comp_time.threads",
    "comp_time.device",
    "comp_time.after_sweep",
    "recipe.bf16",
    "real_data",
)


def resolve_path(path: str | Path, base: Path | None = None) -> Path:
    """``path`` with ``~`` expanded, made absolute against ``base`` (the launch directory; default: the current
    directory, which is the launch directory once a job has started, :func:`ablate.jobs.job.in_launch_dir`) if it is
    relative."""
    path = Path(os.path.expanduser(str(path)))
    return path if path.is_absolute() else (base or Path.cwd()) / path


#: Overrides that never name a row: the seed, the scale, the table, and options that change no number.
NOT_A_ROW = ("seed", "scale", "force", "experiment", "hydra", "logger", "trainer.enable_progress_bar")


def row_name(overrides: Iterable[str], swept: Iterable[str] | None, choice: str | None = None) -> str:
    """The table row a job fills, as its run's ``row`` tag; the job (:mod:`ablate.jobs.spec`) and the racing sweeper
    both name rows with it. ``overrides``: the job's own (``key=value``); ``swept``: the keys the sweep sweeps over
    (None: not a sweep); ``choice``: the config's ``row`` choice, where a table's rows are configs.

    The ``row`` choice (or a ``row=`` override) is the row; else, in a sweep, the swept overrides but the seed,
    sorted (``fusion=sum``); else the job's own overrides but :data:`NOT_A_ROW`; else ``default``."""
    items = [o.lstrip("+~") for o in overrides]
    keyed = [(item.split("=", 1)[0], item) for item in items]
    given = [item.split("=", 1)[1] for key, item in keyed if key == "row" and "=" in item]
    if choice or given:
        return str(choice or given[-1])
    if swept is not None:
        keys = set(swept) - {"seed"}
        own = [item for key, item in keyed if key in keys]
    else:
        own = [item for key, item in keyed if not key.startswith(NOT_A_ROW)]
    return " ".join(sorted(own)) or "default"


#: How a run's ``tuned_config`` tag names a value one of the job's experts was tuned to (``experts.<modality>.<key>``),
#: beside the job's own tuned values (the config's keys).
EXPERT_TUNED = "experts."


def tuned_key(name: str, modality: str | None = None) -> str:
    """The key of a tuned value in a run's ``tuned_config`` tag: the config's own key ``name``
    (``task.optimizer.lr``), or ``experts.<modality>.<name>`` for the value the job's ``modality`` expert was tuned to
    (the job's ``experts.draws.<modality>``, :mod:`ablate.sweep.tuning`). :func:`split_tuned_key` reads it back."""
    return f"{EXPERT_TUNED}{modality}.{name}" if modality else name


def split_tuned_key(key: str) -> tuple[str | None, str]:
    """(the expert's modality or None, the config's key) of a ``tuned_config`` key made by :func:`tuned_key`."""
    if not key.startswith(EXPERT_TUNED):
        return None, key
    modality, name = key.removeprefix(EXPERT_TUNED).split(".", 1)
    return modality, name


def config_hash(cfg: DictConfig) -> str:
    """A short, stable hash of the resolved config without the keys in :data:`UNHASHED`, its numerics resolved
    for this machine (:func:`ablate.hardware.resolved`: ``auto`` is hashed as what it becomes here)."""
    data = OmegaConf.to_container(hardware.resolved(cfg), resolve=True)
    for dotted in UNHASHED:
        *path, last = dotted.split(".")
        node = data
        for key in path:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(last, None)
    return hashlib.sha1(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:12]


def flatten(data: Any, prefix: str = "") -> dict[str, str]:
    """Flatten nested dicts / lists into ``a.b.0.c -> str(value)``, as MLflow params."""
    out: dict[str, str] = {}
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else None
    if items is None:
        return {prefix: str(data)}
    for key, value in items:
        name = f"{prefix}.{key}" if prefix else str(key)
        out.update(flatten(value, name))
    return out


def git_commit(where: str | Path | None = None) -> str:
    """The git commit of the checkout at ``where`` (default: the current directory), with ``-dirty`` when tracked
    files have changes, or ``unknown`` outside a checkout. ``results/`` and the top-level ``README.md`` do not
    count: a published sweep writes its tables into the one and their summary lines into the other
    (:mod:`ablate.tables.index`), outputs that would otherwise mark every run of the next sweep dirty."""
    cwd = None if where is None else str(where)
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=cwd
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!results", ":!README.md"],
            capture_output=True,
            text=True,
            check=True,
            cwd=cwd,
        ).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


@lru_cache(maxsize=1)
def code_version() -> dict[str, str]:
    """The ``ablate`` that runs: ``{"version": <installed version>, "commit": <its checkout's commit>}``, the commit
    ``unknown`` when ``ablate`` is not imported from a git checkout (a wheel). Cached per process: the code of a
    running process does not change under it."""
    is_checkout = (SOURCE / ".git").exists() and (SOURCE / "ablate" / "__init__.py").is_file()
    return {"version": __version__, "commit": git_commit(SOURCE) if is_checkout else "unknown"}


def mlflow_tags() -> dict[str, str]:
    """MLflow's standard tags, which its UI shows as a run's Source, Version and User
    (https://mlflow.org/docs/latest/ml/tracking/tracking-api/#system-tags): the commit of the ``ablate`` that ran
    (without ``-dirty``; ``git_commit`` keeps that), the command, the user."""
    commit = code_version()["commit"].removesuffix("-dirty")
    tags = {"mlflow.source.name": "python -m ablate", "mlflow.source.type": "LOCAL", "mlflow.user": getpass.getuser()}
    return tags | ({"mlflow.source.git.commit": commit} if commit != "unknown" else {})


def provenance_tags(launch: Path | None = None) -> dict[str, str]:
    """The tags a run records about its code: ``git_commit`` (the ``ablate`` checkout that ran, :func:`code_version`),
    ``ablate_version``, and ``launch_commit`` (the launch directory's own checkout, where it is one and another;
    ``launch`` defaults to the current directory)."""
    code = code_version()
    tags = {"git_commit": code["commit"], "ablate_version": code["version"], **mlflow_tags()}
    here = git_commit(launch or Path.cwd())
    if here != "unknown" and here.removesuffix("-dirty") != code["commit"].removesuffix("-dirty"):
        tags["launch_commit"] = here
    return tags
