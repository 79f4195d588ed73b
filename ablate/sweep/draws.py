"""A tuning phase's draws: trial k's value of each parameter of a search space, the same for every row of a table.

The search space is Hydra's override grammar, one sweep per parameter (``table.tune.space``, for example
``{task.optimizer.lr: "tag(log, interval(1e-4, 1e-2))", task.optimizer.weight_decay: "interval(0, 1e-3)",
trainer.max_epochs: "choice(2, 4)"}``): ``interval(lo, hi)`` draws uniformly (an int interval an integer), with
``tag(log, ...)`` log-uniformly; ``choice(...)`` one of its options, each as likely.

Common random numbers (as DomainBed's ``hparams_registry``): the uniform number behind parameter p at trial k is
drawn from a generator seeded by (the tuning seed, the table, p's name, k) alone, never by the row, so every row of a
table gets the same draws of the parameters they share, and adding a parameter to the space leaves the others'
draws as they were. Trial 0 is the recipe itself (no override): every row's tuning includes the config it would
race with untuned.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep
from hydra.errors import HydraException


def _uniform(seed: int, table: str, name: str, trial: int) -> float:
    """The uniform number in [0, 1) behind parameter ``name`` at ``trial`` of ``table``'s tuning."""
    key = [int(seed), zlib.crc32(table.encode()), zlib.crc32(name.encode()), int(trial)]
    return float(np.random.default_rng(key).random())


def _value(sweep: Any, u: float, name: str) -> Any:
    """The value at uniform ``u`` of one parameter's sweep."""
    if isinstance(sweep, ChoiceSweep):
        options = list(sweep.list)
        return options[min(int(u * len(options)), len(options) - 1)]
    if isinstance(sweep, IntervalSweep):
        if sweep.start is None or sweep.end is None:
            raise ValueError(f"table.tune.space.{name}: an interval needs a start and an end")
        lo, hi = float(sweep.start), float(sweep.end)
        if "log" in sweep.tags:
            if lo <= 0:
                raise ValueError(f"table.tune.space.{name}: a log interval needs a positive start, got {sweep.start}")
            value = math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            value = lo + u * (hi - lo)
        if isinstance(sweep.start, int) and isinstance(sweep.end, int):
            return min(int(math.floor(value)), int(sweep.end) - 1) if hi > lo else int(lo)
        return float(f"{value:.4g}")  # four significant digits: a config a person reads
    raise ValueError(f"table.tune.space.{name}: {sweep!r} is not an interval(...) or a choice(...)")


def parse_space(space: Mapping[str, str]) -> dict[str, Any]:
    """Each parameter's sweep, parsed by Hydra's override grammar; one clear error naming a parameter that does not
    parse or is not a sweep."""
    parser = OverridesParser.create()
    out = {}
    for name, text in space.items():
        try:
            override = parser.parse_override(f"{name}={text}")
        except HydraException as err:  # the grammar's own error (OverrideParseException among them)
            raise ValueError(f"table.tune.space.{name}: {text!r} does not parse: {err}") from None
        if not override.is_sweep_override():
            raise ValueError(f"table.tune.space.{name}: {text!r} is a value, not an interval(...) or a choice(...)")
        out[name] = override.value()
    return out


def draw(space: Mapping[str, str], table: str, seed: int, trial: int) -> dict[str, Any]:
    """Trial ``trial``'s overrides ({parameter: value}); trial 0: none, the recipe."""
    if trial == 0:
        return {}
    return {name: _value(sweep, _uniform(seed, table, name, trial), name) for name, sweep in parse_space(space).items()}
