"""What a sweep launches, worked out once: its rows, the keys that name them, its race and tuning phase, and the jobs
of each launch.

The racing sweeper (``hydra_plugins/ablate_racing_sweeper``) builds one :class:`SweepPlan` from its config and command
line before any job runs, and launches from it: the rows' jobs are the product of the swept values (the sweeper's
``params``, a table's rows and the command line together, a key on the command line winning), as Hydra's basic
sweeper splits them; a table that races its seeds (``table.seeds``) launches them look by look
(:func:`look_jobs`), after its tuning phase where it tunes (``table.tune``, :mod:`ablate.sweep.tuning`: the experts'
trials, then stage 2's, trial k of every row a launch, :meth:`ablate.sweep.tuning.TuneSpec.batch`). The same plan
gives the jobs known before the first look ends (:meth:`SweepPlan.jobs`), which the sweep's progress counts and its
estimate composes (:mod:`ablate.sweep.progress`, :mod:`ablate.sweep.plan`). Building it reads nothing but the
config files; a resumed tuning phase's choices come from the store's objectives, passed in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from ablate.config import composer
from ablate.store import row_name
from ablate.sweep.tuning import Experts, TuneSpec, choices, stage2_rows
from ablate.tables import table_spec
from ablate.tables.raceplan import RacePlan
from ablate.tables.spec import LOWER_IS_BETTER, sweep_params


def look_jobs(jobs: Mapping[str, list[str]], racing: Sequence[str], have: Mapping[str, int], n: int) -> list[list[str]]:
    """A look's jobs: each row of ``racing`` (its overrides but the seed in ``jobs``) at the seeds from the ``have``
    it has to ``n``, row by row."""
    return [[*jobs[row], f"seed={seed}"] for row in racing for seed in range(have.get(row, 0), n)]


@dataclass(frozen=True)
class SweepPlan:
    """A sweep's launches. ``table``: the table's name; ``combos``: every combination of the swept values, in the
    order Hydra's basic sweeper splits them; ``swept``: the keys swept (the rows' names, :func:`ablate.store.row_name`);
    ``race``: the table's racing plan (None: every combination at once, as an ad-hoc sweep or a command line that
    names ``seed``); ``tune``: its tuning phase (None: none); ``experts``: where its rows sit on experts (tuned first);
    ``reference``: the row (or the rows, the best of them) the others are compared with; ``higher``: whether a
    higher primary metric is better; ``seeded``: a table that races, swept at the seeds its command line names
    (then every job at once)."""

    table: str
    combos: list[list[str]]
    swept: frozenset[str]
    race: RacePlan | None = None
    tune: TuneSpec | None = None
    experts: Experts = field(default_factory=Experts)
    reference: str | list[str] = ""
    higher: bool = True
    seeded: bool = False

    @classmethod
    def of(
        cls, config: DictConfig, arguments: Sequence[str], params: Mapping[str, Any], config_loader: Any = None
    ) -> SweepPlan:
        """The plan of the sweep of ``config`` with the command line's ``arguments`` and the sweeper's ``params``
        (``config_loader``: Hydra's, for the overrides' functions). A bad ``table.seeds`` or ``table.tune`` is one
        ValueError naming the option."""
        params = sweep_params(params, list(arguments), config.table)  # a table's rows (ablate.tables.spec.run_rows)
        lines = [f"{key}={value}" for key, value in params.items()] + list(arguments)
        overrides = OverridesParser.create(config_loader=config_loader).parse_overrides(lines)
        combos = [list(c) for batch in BasicSweeper.split_arguments(overrides, None) for c in batch]
        swept = frozenset(o.get_key_element().lstrip("+~") for o in overrides if o.is_sweep_override())
        table = table_spec(config)
        race = RacePlan.of_table(config)
        seeded = "seed" in {o.get_key_element().lstrip("+~") for o in overrides}
        if race is None or seeded:
            return cls(str(table.name), combos, swept, seeded=race is not None)
        given = table.get("tune")
        tune = TuneSpec.from_config(OmegaConf.to_container(given, resolve=True) if given else None)  # type: ignore[arg-type]
        rows = [row_name(c, swept) for c in combos]
        named = table.get("reference")
        candidates = [named] if isinstance(named, str) else list(named or [])
        reference: str | list[str] = [r for r in candidates if r in rows] or rows[0]
        jobs = dict(zip(rows, combos, strict=True))
        if table.get("tuned_from") == "published":  # every row on its published config, no tuning phase
            if tune is not None:
                raise ValueError("table.tuned_from=published races on the published configs: leave tune= out")
            from ablate.analysis.reproduce import published_configs  # the records: pandas

            on = published_configs(str(table.name), jobs, composer(config))
            combos = [[*c, *on[row]] for row, c in zip(rows, combos, strict=True)]
            jobs = dict(zip(rows, combos, strict=True))
        experts = Experts.of(jobs, composer(config)) if tune is not None and tune.experts else Experts()
        higher = table.primary not in LOWER_IS_BETTER
        return cls(str(table.name), combos, swept, race, tune, experts, reference, higher)

    @classmethod
    def of_config(cls, config: DictConfig) -> SweepPlan:
        """The plan of the multirun of ``config`` as its sweeper builds it: the sweeper's ``params`` and the command
        line's overrides (``hydra.overrides.task``) are the config's."""
        params = OmegaConf.select(config, "hydra.sweeper.params", default=None) or {}
        return cls.of(config, list(config.hydra.overrides.task), dict(params))

    def trials(self, part: Mapping[str, list[str]]) -> list[list[str]]:
        """The trials' jobs of one part of the tuning phase (``part``: row -> overrides), as it launches them: trial k
        of every row, k = 0 .. N-1; where it halves (:mod:`ablate.sweep.halving`), each rung's as many trials per row
        as the rung keeps, those before the promotions are known standing for them (trials 0, 1, ...)."""
        assert self.tune is not None
        spec, halving = self.tune, self.tune.halving
        if halving is None:
            return [job for k in range(spec.trials) for job in spec.batch(self.table, part, k)]
        return [
            [*overrides, *spec.overrides(self.table, k, r)]
            for r, keep in enumerate(halving.counts(spec.trials))
            for k in range(keep)
            for overrides in part.values()
        ]

    @property
    def rows(self) -> dict[str, list[str]]:
        """Each row's jobs' overrides (but the seed, where the sweep races), in the sweep's order."""
        return {row_name(c, self.swept): list(c) for c in self.combos}

    def jobs(self, objectives: Mapping[str, Mapping[int, float]] | None = None) -> list[list[str]]:
        """Every job's overrides known before the first look ends, in launch order: every combination at once
        where the sweep does not race; else the tuning phase's trials (every expert's, then stage 2's) and the first
        look. Given the tuning trials' ``objectives`` in the store (row -> trial -> value: a resumed phase's),
        stage 2's trials sit on the experts' chosen draws and the raced jobs on their rows' chosen trials, as the
        sweeper launches them once it has chosen (:func:`ablate.sweep.tuning.choices`); without them, on the
        recipe."""
        if self.race is None:
            return [list(c) for c in self.combos]
        rows = self.rows
        raced: Mapping[str, list[str]] = dict.fromkeys(rows, [])
        trials: list[list[str]] = []
        if self.tune is not None:
            fixed: list[str] = []
            if objectives:
                done = (self.tune.trials, self.tune.trials)
                tuned = choices(self.tune, self.table, rows, self.experts, objectives, done, self.higher)
                fixed, raced = tuned.fixed, tuned.overrides
            for part in (self.experts.trials(), stage2_rows(rows, self.experts, fixed)):  # as the phase runs
                trials += self.trials(part)
        on = {row: [*jobs, *raced[row]] for row, jobs in rows.items()}
        return trials + look_jobs(on, list(rows), {}, self.race.first)
