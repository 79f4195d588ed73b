"""The racing sweeper's config (``hydra/sweeper=racing``, the default of ``python -m ablate -m``).

The race's plan is the table's (``table.seeds``, :class:`ablate.tables.raceplan.RacePlan`), not the sweeper's: the
table and the sweeper then read one plan. ``params`` are swept as Hydra's basic sweeper sweeps them.
"""

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore


@dataclass
class RacingSweeperConf:
    _target_: str = "hydra_plugins.ablate_racing_sweeper.racing_sweeper.RacingSweeper"
    #: the swept keys and their values, as ``hydra.sweeper.params`` of the basic sweeper
    params: dict[str, Any] | None = field(default=None)
    #: at most this many jobs handed to the launcher at once (submitit starts every job it is given); null: a look
    max_batch_size: int | None = None


ConfigStore.instance().store(group="hydra/sweeper", name="racing", node=RacingSweeperConf, provider="ablate")
