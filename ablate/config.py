"""The root config of ``python -m ablate`` (``conf/``), composed outside a Hydra app: for the report, the latency
timing and the diagnosis, which run after the jobs."""

from __future__ import annotations

import copy
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

#: The configs: inside the package (a wheel ships them; in a checkout ablate/conf is the project's conf/ folder).
CONF = Path(__file__).resolve().parent / "conf"
#: The results folder, relative to the directory a command runs in (a checkout's ``results/``); what is written
#: there goes through :mod:`ablate.tables.published`, but for the data tools' own ``--out`` defaults.
RESULTS = Path("results")


#: Configs composed by this process, by where they were composed and their overrides (:func:`compose`); at most
#: :data:`KEPT` of them, the least recently used dropped first.
_composed: OrderedDict[tuple, DictConfig] = OrderedDict()
KEPT = 512


def compose(overrides: Sequence[str]) -> DictConfig:
    """The root config of ``python -m ablate`` with ``overrides``, composed outside a Hydra app.

    A sweep's plan, its tuning phase, its table and the report compose the same jobs' configs again and again (a
    plan at every look, each row for its latency and its footer), about 0.2 s each on a 2-core AMD EPYC (family 25,
    model 1). So each composition is kept for the life of the process, keyed by its overrides and the config
    sources it was composed from (in any order where each key is set once: :func:`_canonical`), and a copy is
    returned (a caller may change it). A config folder edited while a process runs is not read again by that
    process."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    hydra = GlobalHydra.instance()
    inside = hydra.is_initialized()  # inside the running app (a sweep's end): its own config source
    sources = (
        tuple((s.provider, s.path) for s in hydra.config_loader().get_sources()) if inside else (("main", str(CONF)),)
    )
    key = (sources, _canonical(overrides))
    if key not in _composed:
        if inside:
            made = hydra_compose("config", overrides=list(overrides))
        else:
            with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
                made = hydra_compose("config", overrides=list(overrides))
        _composed[key] = made
        if len(_composed) > KEPT:
            _composed.popitem(last=False)
    _composed.move_to_end(key)
    return copy.deepcopy(_composed[key])


def _canonical(overrides: Sequence[str]) -> tuple:
    """``overrides`` as a cache key that names the same config the same way: where each key is set once and none
    lies inside another (Hydra then composes the same config in any order), nothing is swept and no group is
    appended (``+group=option``: the defaults list keeps their order), the parsed overrides sorted by key, each
    value as Hydra reads it (a sweep's jobs say ``publish=False`` where the command line said ``publish=false``,
    and list the row first); otherwise the overrides as given, in their order."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    given = ("as given", tuple(overrides))
    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
        keys = [(o.key_or_group, str(o.package)) for o in parsed]
        names = [k for k, _ in keys]
        nested = any(a.startswith(b + ".") for a in names for b in names)
        if nested or len(set(keys)) < len(keys) or any(o.is_sweep_override() or o.is_add() for o in parsed):
            return given
        return ("by key", tuple(sorted((*k, o.type.name, repr(o.value())) for k, o in zip(keys, parsed, strict=True))))
    except Exception:  # overrides Hydra cannot read: composing them says what is wrong
        return given


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
