"""A race's plan (``table.seeds``, :class:`RacePlan`): its looks, the error rate of one comparison, and how that rate
is split over the looks. The race itself (:func:`ablate.tables.racing.race`) tests each look at the plan's level.

The plan is ``table.seeds`` (``{looks: [3, 5, 8], alpha: 0.05, correction: bonferroni, budget_min: 120}``): at
look k every row still racing has seeds ``0 .. looks[k]-1``.

Repeated looks at accumulating data inflate the error rate: uncorrected, three looks at alpha = 0.05 each declare
a difference between two identical rows about 11 % of the time. The correction splits ``alpha`` over the planned
looks, so that by the union bound a comparison of two identical rows is declared at some look with probability at
most ``alpha``:

* ``bonferroni`` (the default): ``alpha / K`` at each of the K looks;
* ``pocock``: the increments of Lan & DeMets' Pocock-type spending function ``alpha * ln(1 + (e - 1) t)``
  (Lan & DeMets 1983, Biometrika 70(3), eq. for alpha_2*), at the information times ``t_k = n_k / n_K``;
* ``obrien_fleming``: the increments of the O'Brien-Fleming-type spending function
  ``2 - 2 Phi(z_{1 - alpha/2} / sqrt(t))`` (same paper), which keeps most of ``alpha`` for the last look;
* ``none``: ``alpha`` at every look, which does not hold the error rate (kept to show why a correction is needed).

Reading chosen: the spending increments are used as nominal per-look levels of the t-test (a union bound), not as
exact group-sequential boundaries, which at 3-8 seeds with an unknown variance have no closed form; the union
bound is conservative (about 4 % false positives at looks 3, 5, 8 in simulation).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from scipy import stats

from ablate.tables.verdicts import MULTIPLICITY

CORRECTIONS = ("bonferroni", "pocock", "obrien_fleming", "none")


@dataclass(frozen=True)
class RacePlan:
    """The looks (seeds per row at each), the error rate ``alpha`` of one comparison, its correction over the
    looks, and the wall-time budget of the race in minutes (None: none)."""

    looks: tuple[int, ...]
    alpha: float = 0.05
    correction: str = "bonferroni"
    budget_min: float | None = None
    rope: float | None = None  # δ of the table's region of practical equivalence (table.rope.delta); None: none
    multiplicity: str = "holm"  # the correction over a table's comparisons (ablate.tables.verdicts)

    def __post_init__(self) -> None:
        looks = list(self.looks)
        if not looks or any(not isinstance(n, int) or isinstance(n, bool) or n < 1 for n in looks):
            raise ValueError(f"table.seeds.looks: {looks} must be a non-empty list of positive integers")
        if looks != sorted(set(looks)):
            raise ValueError(f"table.seeds.looks: {looks} must increase strictly")
        if not 0 < self.alpha < 1:
            raise ValueError(f"table.seeds.alpha: {self.alpha} must lie between 0 and 1")
        if self.correction not in CORRECTIONS:
            raise ValueError(f"table.seeds.correction: {self.correction!r} is not one of {', '.join(CORRECTIONS)}")
        if self.budget_min is not None and self.budget_min <= 0:
            raise ValueError(f"table.seeds.budget_min: {self.budget_min} must be positive (or null: no budget)")
        if self.rope is not None and not self.rope > 0:
            raise ValueError(f"table.rope.delta: {self.rope} must be positive (or null: no region of equivalence)")
        if self.multiplicity not in MULTIPLICITY:
            raise ValueError(f"table.seeds.multiplicity: {self.multiplicity!r} is not one of {', '.join(MULTIPLICITY)}")

    @classmethod
    def from_config(cls, seeds: Mapping[str, Any] | None) -> RacePlan | None:
        """The plan of ``table.seeds``, or None where the table does not race."""
        if not seeds:
            return None
        unknown = set(seeds) - {"looks", "alpha", "correction", "budget_min", "multiplicity"}
        if unknown:
            raise ValueError(f"table.seeds: unknown option(s) {', '.join(sorted(unknown))}")
        budget = seeds.get("budget_min")
        return cls(
            tuple(seeds.get("looks") or ()),
            float(seeds.get("alpha", 0.05)),
            str(seeds.get("correction", "bonferroni")),
            None if budget is None else float(budget),
            multiplicity=str(seeds.get("multiplicity", "holm")),
        )

    def with_rope(self, table: Mapping[str, Any] | DictConfig | None) -> RacePlan:
        """This plan with the δ of ``table`` (``table.rope.delta``; none where the table states none)."""
        rope = (table or {}).get("rope") or {}
        delta = rope.get("delta") if isinstance(rope, Mapping | DictConfig) else None
        return replace(self, rope=None if delta is None else float(delta))

    @classmethod
    def of_table(cls, cfg: DictConfig) -> RacePlan | None:
        """The plan of a composed config's table (``table.seeds``, which experiments take from ``scale.race``): the
        one source of a table's seeds, for the racing sweeper, the tables, the diagnosis and the capacity plan."""
        seeds = cfg.table.get("seeds")
        plan = cls.from_config(OmegaConf.to_container(seeds, resolve=True) if seeds is not None else None)  # type: ignore[arg-type]
        return plan.with_rope(cfg.table) if plan is not None else None

    @property
    def first(self) -> int:
        """The seeds every row gets: the first look's."""
        return self.looks[0]

    def levels(self) -> list[float]:
        """The nominal level of each look's test; they add up to ``alpha`` (but for ``none``)."""
        k = len(self.looks)
        if self.correction == "none":
            return [self.alpha] * k
        if self.correction == "bonferroni":
            return [self.alpha / k] * k
        t = np.asarray(self.looks, dtype=float) / self.looks[-1]
        if self.correction == "pocock":
            spent = self.alpha * np.log1p((math.e - 1) * t)
        else:
            spent = 2 - 2 * stats.norm.cdf(stats.norm.ppf(1 - self.alpha / 2) / np.sqrt(t))
        return [float(x) for x in np.diff(np.concatenate([[0.0], spent]))]

    def describe(self) -> str:
        """One sentence for a table's footer."""
        levels = " / ".join(f"{x:.4f}" for x in self.levels())
        how = {
            "bonferroni": "Bonferroni over the planned looks",
            "pocock": "Pocock-type alpha spending (Lan-DeMets)",
            "obrien_fleming": "O'Brien-Fleming-type alpha spending (Lan-DeMets)",
            "none": "no correction for the repeated looks (the error rate is not held)",
        }[self.correction]
        budget = f"; wall-time budget {self.budget_min:g} min" if self.budget_min else ""
        over = {
            "holm": "Holm's step-down over the table's comparisons (family-wise)",
            "bh": "Benjamini-Hochberg over the table's comparisons (false discovery rate)",
            "none": "no correction over the table's comparisons (each holds alpha on its own)",
        }[self.multiplicity]
        tests = (
            f"paired t-tests against 0 and against ±δ = {self.rope:g} (TOST for equivalence)"
            if self.rope is not None
            else "a two-sided paired t-test"
        )
        return (
            f"Racing seeds: looks at {', '.join(map(str, self.looks))} seeds per row, alpha = {self.alpha:g}, "
            f"{how}: per-look levels {levels} of {tests}; {over}{budget}"
        )
