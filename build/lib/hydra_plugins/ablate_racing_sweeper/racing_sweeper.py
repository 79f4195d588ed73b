"""A Hydra sweeper that adds seeds only where a table is undecided (:mod:`ablate.tables.racing`)."""

from __future__ import annotations

from typing import Any

from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class RacingSweeper(Sweeper):
    """Launches a table's (row, seed) jobs look by look through the configured launcher; see
    :class:`hydra_plugins.ablate_racing_sweeper._impl.RacingSweeperImpl`."""

    def __init__(self, params: dict[str, Any] | None = None, max_batch_size: int | None = None) -> None:
        from ._impl import RacingSweeperImpl

        self.sweeper = RacingSweeperImpl(params, max_batch_size)

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.sweeper.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: list[str]) -> Any:
        return self.sweeper.sweep(arguments)
