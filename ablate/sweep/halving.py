"""Successive halving in the tuning phase (``table.tune.halving``): many trials trained briefly, the best fraction
of each row's trained on.

Successive halving (Jamieson & Talwalkar 2016, Algorithm 1; Li et al. 2018, JMLR, Hyperband's inner loop): N
trials run to the first rung's budget; the top 1/η of them by validation go on to the next rung's, and so on to the
full budget; the best of the trials that reached it is chosen. Here a rung is a fraction of the recipe's epochs
(``rungs``, increasing, the last 1). The reading chosen for an ablation's fairness:

* **Every row alike**: the same N trials, the same draws (:mod:`ablate.sweep.draws`), the same rungs and the same
  promotion rule (the top ``ceil(n / η)`` of that row's trials at the rung, by the validation objective, of equals
  the lower trial number; a failed trial last), so a row's count of trials at each rung is every other row's.
* **Resumed, never retrained**: a trial at a rung trains the recipe's schedule (its learning rate decays over all
  the recipe's epochs) and stops at the rung's epoch (``rung=<fraction>``,
  :class:`ablate.jobs.rung_callbacks.StopAtRung`); promoted, it resumes from its checkpoint (the rungs of a trial
  share its checkpoint folder, :attr:`ablate.jobs.spec.JobSpec.ckpt_dir`), so a trial that reaches the last rung
  has trained exactly as a full-budget trial (the preemption resumes' exactness, :mod:`ablate.jobs.generators`)
  and its last rung's run *is* the full-budget trial's (``rung`` null: the same config hash).
* **The objective at a rung** is the best validation value over the epochs trained so far (``val_best``, as a
  full-budget trial's): a trial is judged on what it reached, never on its last epoch alone.
* **Replayable**: every trial's validation value per epoch is kept (tag ``val_curve``, the records'
  ``runs/<table>.trials.csv``): :func:`replay` chooses from full-budget curves as successive halving would have,
  so the two can be compared from one full-budget phase (``bench/bench_halving.py``, ``docs/tuning.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Halving:
    """``table.tune.halving``: the promotion ratio ``eta`` (the top 1/η of a rung go on) and the ``rungs``, fractions
    of the recipe's epochs, increasing, the last 1."""

    eta: int = 3
    rungs: tuple[float, ...] = (1 / 9, 1 / 3, 1.0)

    @classmethod
    def from_config(cls, given: Mapping[str, object] | None) -> Halving | None:
        """The halving of ``table.tune.halving``; None where the phase trains every trial to the full budget. One
        clear error per bad option."""
        if not given:
            return None
        unknown = set(given) - {"eta", "rungs"}
        if unknown:
            raise ValueError(f"table.tune.halving: unknown option(s) {', '.join(sorted(unknown))}")
        eta = given.get("eta", cls.eta)
        if not isinstance(eta, int) or isinstance(eta, bool) or eta < 2:
            raise ValueError(f"table.tune.halving.eta: {eta!r} must be an integer of at least 2")
        rungs = tuple(float(r) for r in given.get("rungs", cls.rungs))  # type: ignore[attr-defined]
        if not rungs or rungs[-1] != 1.0 or any(not a < b for a, b in zip((0.0, *rungs), rungs)):
            raise ValueError(
                f"table.tune.halving.rungs: {list(rungs)} must be increasing fractions of the recipe's epochs, "
                "the last 1 (the full budget)"
            )
        return cls(eta, rungs)

    def counts(self, trials: int) -> list[int]:
        """How many trials of a row train at each rung: N at the first, then ``ceil(n / η)`` of the rung before."""
        out = [trials]
        for _ in self.rungs[1:]:
            out.append(max(1, math.ceil(out[-1] / self.eta)))
        return out

    def rung_epochs(self, epochs: int) -> list[int]:
        """Each rung's last epoch for a recipe of ``epochs`` epochs: the fraction's share, at least 1, rounded."""
        return [max(1, min(epochs, round(f * epochs))) for f in self.rungs]

    def override(self, rung: int) -> list[str]:
        """What a trial at rung ``rung`` adds to its overrides: its fraction, none at the last (the full budget, the
        full-budget trial's own config)."""
        return [] if rung == len(self.rungs) - 1 else [f"++rung={self.rungs[rung]:.6g}"]

    def cost(self, trials: int, epochs: int | None = None) -> float:
        """A row's tuning cost in full-budget trials (each trial's epochs once: promoted trials resume). With the
        recipe's ``epochs``, at its rungs' whole epochs (:meth:`rung_epochs`), as a phase trains: a short recipe
        halves less (6 trials of a 2-epoch recipe cost 3.5 full trials, not 2.33)."""
        ends = [e / epochs for e in self.rung_epochs(epochs)] if epochs else list(self.rungs)
        spans = [b - a for a, b in zip((0.0, *ends), ends)]
        return sum(n * span for n, span in zip(self.counts(trials), spans))

    def describe(self) -> str:
        """The footer's sentence on the rungs."""
        rungs = ", ".join(f"{f:.3g}" for f in self.rungs)
        return (
            f"successive halving: rungs at {rungs} of the recipe's epochs, the top 1/{self.eta} of each row's promoted"
        )


def promote(values: Mapping[int, float], keep: int, higher_is_better: bool = True) -> list[int]:
    """The ``keep`` trials of a rung (``values``: trial -> objective at the rung) that go on, in trial order: the
    best by objective, of equals the lower trial number; a failed trial (NaN) after every scored one."""

    def rank(item: tuple[int, float]) -> tuple[bool, float, int]:
        k, v = item
        failed = math.isnan(v)
        return (failed, 0.0 if failed else (-v if higher_is_better else v), k)

    return sorted(k for k, _ in sorted(values.items(), key=rank)[:keep])


def best_until(curve: Mapping[int, float], epoch: int, higher_is_better: bool = True) -> float:
    """A trial's objective at a rung ending at ``epoch``: its best validation value over epochs 1..``epoch``
    (``curve``: epoch -> value); NaN where none was validated."""
    seen = [v for e, v in curve.items() if e <= epoch and not math.isnan(v)]
    if not seen:
        return math.nan
    return max(seen) if higher_is_better else min(seen)


@dataclass(frozen=True)
class Replay:
    """What successive halving chooses from one row's full-budget curves: each rung's trials, the chosen trial, and
    the epochs it trains in all (each trial's furthest rung) against the full-budget phase's."""

    rungs: list[list[int]]
    chosen: int
    epochs: int
    full_epochs: int


def replay(
    curves: Mapping[int, Mapping[int, float]], halving: Halving, epochs: int, higher_is_better: bool = True
) -> Replay:
    """Successive halving replayed on one row's full-budget trials (``curves``: trial -> epoch -> validation value,
    epochs 1..``epochs``): the choice it would have made and its cost in epochs. Exact where a trial resumed at a
    rung trains as it did in one go (:mod:`ablate.sweep.halving`)."""
    ends = halving.rung_epochs(epochs)
    alive = sorted(curves)
    rungs: list[list[int]] = []
    spent = 0
    values: dict[int, float] = {}
    for r, (end, keep) in enumerate(zip(ends, halving.counts(len(alive)))):
        alive = promote(values, keep, higher_is_better) if r else alive
        rungs.append(alive)
        spent += len(alive) * (end - (ends[r - 1] if r else 0))
        values = {k: best_until(curves[k], end, higher_is_better) for k in alive}
    chosen = promote(values, 1, higher_is_better)[0]
    return Replay(rungs, chosen, spent, epochs * len(curves))


def full_choice(curves: Mapping[int, Mapping[int, float]], epochs: int, higher_is_better: bool = True) -> int:
    """The full-budget phase's choice from the same curves: the best objective over all epochs, of equals the lower
    trial number (:func:`ablate.sweep.tuning.choose`)."""
    values = {k: best_until(c, epochs, higher_is_better) for k, c in curves.items()}
    return promote(values, 1, higher_is_better)[0]


def rung_batches(rows: Sequence[str], alive: Mapping[str, Sequence[int]]) -> list[list[tuple[str, int]]]:
    """A rung's launches: the i-th trial alive of every row as one batch, i = 0, 1, ... (every row has as many)."""
    width = max((len(alive[r]) for r in rows), default=0)
    return [[(r, alive[r][i]) for r in rows if i < len(alive[r])] for i in range(width)]
