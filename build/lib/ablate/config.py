"""The root config of ``python -m ablate`` (``conf/``), composed outside a Hydra app: for the report, the latency
timing and the diagnosis, which run after the jobs."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

#: The configs: inside the package (a wheel ships them; in a checkout ablate/conf is the project's conf/ folder).
CONF = Path(__file__).resolve().parent / "conf"


def compose(overrides: list[str]) -> DictConfig:
    """The root config of ``python -m ablate`` with ``overrides``, composed outside a Hydra app."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside the running app (a sweep's end): its own config source
        return hydra_compose("config", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose("config", overrides=overrides)
