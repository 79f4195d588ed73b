"""The root config of ``python -m ablate`` (``conf/``), composed outside a Hydra app: for the report, the latency
timing and the diagnosis, which run after the jobs."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

#: The configs: inside the package (a wheel ships them; in a checkout ablate/conf is the project's conf/ folder).
CONF = Path(__file__).resolve().parent / "conf"
#: The results folder, relative to the directory a command runs in (a checkout's ``results/``); what is written
#: there goes through :mod:`ablate.tables.published`, but for the data tools' own ``--out`` defaults.
RESULTS = Path("results")


def compose(overrides: Sequence[str]) -> DictConfig:
    """The root config of ``python -m ablate`` with ``overrides``, composed outside a Hydra app."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside the running app (a sweep's end): its own config source
        return hydra_compose("config", overrides=list(overrides))
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose("config", overrides=list(overrides))


def searchpath(config: DictConfig) -> list[str]:
    """The override that carries a sweep's own config folders (``hydra.searchpath=[file://myconf]`` on its command
    line) into a config composed again from that sweep's overrides: its plan, its tuning phase, its latency timing
    and its table. Empty where the sweep had none."""
    paths = OmegaConf.select(config, "hydra.searchpath", default=None)
    if not paths:
        return []
    quoted = ["'" + str(p).replace("\\", "\\\\").replace("'", "\\'") + "'" for p in paths]
    return [f"hydra.searchpath=[{','.join(quoted)}]"]


def composer(config: DictConfig) -> Callable[[Sequence[str]], DictConfig]:
    """:func:`compose` within the sweep of ``config``: with its own config folders (:func:`searchpath`) unless the
    overrides name their own."""
    extra = searchpath(config)

    def composed(overrides: Sequence[str]) -> DictConfig:
        own = any(o.startswith("hydra.searchpath=") for o in overrides)
        return compose([*overrides, *([] if own else extra)])

    return composed


def composition_error(err: Exception) -> str:
    """A config that does not compose, in one line: Hydra's first line (``Could not find 'experiment/mine'``), and
    where a user's own configs are looked for."""
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return f"{first} (configs are looked for in {CONF} and in the folders of hydra.searchpath=[file://...])"
