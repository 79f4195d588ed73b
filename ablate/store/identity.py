"""Who made a run and with what: the config hash, the params, the launch directory, and the code's version.

A run records the version of the ``ablate`` that ran (:func:`code_version`: the installed version and, where its
source is a git checkout, that checkout's commit with ``-dirty``), and apart from it the launch directory's own
commit where the launch directory is a checkout (:func:`git_commit`). A sweep launched from a folder that is not a
git repository, with ``ablate`` installed from a checkout, so still records the commit of the code that ran.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from functools import lru_cache
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from ablate import __version__, hardware

#: The checkout ``ablate`` is imported from, when it is one (an editable install or a clone on ``sys.path``).
SOURCE = Path(__file__).resolve().parents[2]

#: Config keys that do not change a result, so they are left out of the config hash (``table`` holds only
#: the paper's numbers and row names; the experiment a run lands in already separates tables; the float32 feature
#: cache of frozen experts, ablate.jobs.experts.FeatureCache, changes the speed only).
UNHASHED = (
    "force",
    "logger",
    "hydra",
    "table",
    "scale.race",
    "trainer.enable_progress_bar",
    "data.num_workers",
    "experts.cache_features",
    "experts.cache_max_gb",
    "comp_time.threads",
    "comp_time.device",
    "comp_time.after_sweep",
    "recipe.bf16",
)


def launch_dir() -> Path:
    """The directory the command was launched from: Hydra's original working directory
    (``hydra.utils.get_original_cwd()``, the config's ``hydra.runtime.cwd``), else the current one.

    Hydra sets ``hydra.runtime.cwd`` where it composes a job's config (``ConfigLoaderImpl.load_configuration``):
    hydra-ray-launcher composes every job in the driver before shipping it, so a Ray job on a cluster started
    elsewhere still sees the driver's directory; submitit composes in the job, which starts in the submitting
    directory (SLURM's default working directory is the one ``sbatch`` ran in).
    """
    return Path(get_original_cwd() if HydraConfig.initialized() else os.getcwd())


def resolve_path(path: str | Path) -> Path:
    """``path`` with ``~`` expanded, made absolute against :func:`launch_dir` if it is relative."""
    path = Path(os.path.expanduser(str(path)))
    return path if path.is_absolute() else launch_dir() / path


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
    files have changes, or ``unknown`` outside a checkout. ``results/`` does not count: the tables a sweep writes
    there are outputs, and would otherwise mark every run of the next sweep dirty."""
    cwd = None if where is None else str(where)
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=cwd
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!results"],
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


def provenance_tags() -> dict[str, str]:
    """The tags a run records about its code: ``git_commit`` (the ``ablate`` checkout that ran, :func:`code_version`),
    ``ablate_version``, and ``launch_commit`` (the launch directory's own checkout, where it is one and another)."""
    code = code_version()
    tags = {"git_commit": code["commit"], "ablate_version": code["version"]}
    here = git_commit(launch_dir())
    if here != "unknown" and here.removesuffix("-dirty") != code["commit"].removesuffix("-dirty"):
        tags["launch_commit"] = here
    return tags
