"""How much of another CPU's kernels' variance a table's verdicts bear, where the table has not measured it.

A seed trained on another CPU's kernels lands elsewhere (docs/verdicts.md), partly by a shift every seed of a
comparison shares (BiFNet Table IV's on an Intel Xeon: ``bench/measured/``).
Where a table measured it (``bench/kernel_spread.py``), its tests add both parts to each paired difference, the
seeds' own ``k`` and the shared ``c``: ``se = sqrt((s² + k²) / n + c² + f²)``
(:func:`ablate.tables.verdicts.paired_tests`); the shared part does not shrink with more seeds. Where it did not,
its verdicts hold for its records' CPU alone. :func:`kernels_margin` says how far they would hold elsewhere: the
largest shared ``c`` at which the race, replayed on the same records with ``c`` added, reaches every claim it
reached without (the same verdict of each comparison that had one; at a later look where the records have its
seeds), and the comparison that changes first beyond it. Wider intervals only take claims away, so the claims that
hold at ``c`` hold below it, and a bisection finds the edge. A table whose measured shift falls below this margin
keeps its verdicts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ablate.tables.racing import RaceState
from ablate.tables.verdicts import UNDECIDED

#: The bisection stops where the edge is known to this share of itself.
PRECISION = 0.005
#: A margin past this many times the largest claimed |Δ| is reported as unbounded (no claim would change).
UNBOUNDED = 1000.0


@dataclass(frozen=True)
class Margin:
    """The largest shared kernels' sd every claim bears (``sd``, a lower bound to :data:`PRECISION`; ``math.inf`` where no
    claim would change), and the comparison that changes first beyond it (``a`` vs ``b``, with its seeds' own sd)."""

    sd: float
    a: str = ""
    b: str = ""
    seeds_sd: float = math.nan

    def words(self, names: dict[str, str], label: str) -> str:
        """The footer's sentence: the margin, and the comparison it binds."""
        if math.isinf(self.sd):
            return "No claim would change whatever another CPU's kernels added (ablate.tables.margin)."
        ratio = f", {floor_2(self.sd / self.seeds_sd):g} times its seeds' own sd" if self.seeds_sd > 0 else ""
        return (
            f"Every claim would still hold with another CPU's kernels shifting every seed's paired difference alike "
            f"by an sd of up to {floor_2(self.sd):g} {label}; beyond it {names.get(self.a, self.a)} vs "
            f"{names.get(self.b, self.b)} changes first{ratio} (ablate.tables.margin)."
        )


def floor_2(x: float) -> float:
    """``x`` rounded down to two significant figures (a margin is never shown larger than it is)."""
    if x <= 0 or not math.isfinite(x):
        return x
    scale = 10 ** (math.floor(math.log10(x)) - 1)
    return math.floor(x / scale * (1 + 1e-12)) * scale


def claims(state: RaceState) -> dict[frozenset, str]:
    """The verdict of each comparison that reached one (two paired seeds or more, not undecided)."""
    return {key: c.kind for key, c in state.comparisons.items() if c.kind != UNDECIDED and c.n >= 2}


def kernels_margin(replay_at: Callable[[float], RaceState]) -> Margin | None:
    """The largest sd at which ``replay_at(sd)`` (the table's race replayed with a shift of that sd shared by every
    seed's paired difference) reaches every claim ``replay_at(0)`` reached; None where it reached none."""
    base = replay_at(0.0)
    made = claims(base)
    if not made:
        return None

    def first_lost(sd: float) -> frozenset | None:
        now = replay_at(sd).comparisons
        lost = [key for key, kind in made.items() if key not in now or now[key].kind != kind]
        return lost[0] if lost else None

    spread = [base.comparisons[key] for key in made]
    cap = UNBOUNDED * max(max(abs(c.delta) for c in spread), max((c.sd for c in spread), default=0.0), 1e-9)
    hi = max(max((c.sd for c in spread if c.sd > 0), default=0.0), cap / UNBOUNDED)
    while (lost := first_lost(hi)) is None:
        if hi > cap:
            return Margin(math.inf)
        hi *= 2
    lo = 0.0
    while hi - lo > PRECISION * hi:
        mid = (lo + hi) / 2
        if (now_lost := first_lost(mid)) is None:
            lo = mid
        else:
            hi, lost = mid, now_lost
    c = base.comparisons[lost]
    return Margin(lo, c.a, c.b, c.sd)


def shift_parts(pairs: list[np.ndarray]) -> tuple[float, float]:
    """A table's two kernels' terms from its reruns on other kernels (``bench/kernel_spread.py``): ``pairs`` holds, per
    pair of rows (and per other CPU measured), the shift of each seed's paired difference from its record. Returns
    (``kernels_sd``, ``kernels_cpu``): the seeds' own sd about their pair's mean shift (pooled within pairs), and the
    sd of the pair's shift shared by its seeds, the mean squared mean shift less what the seeds' own part puts in a
    mean of ``n`` (a one-way random-effects reading; 0 where that is negative)."""
    used = [np.asarray(p, dtype=float) for p in pairs if len(p)]
    if not used:
        return 0.0, 0.0
    dof = sum(len(p) - 1 for p in used)
    within = sum(float(((p - p.mean()) ** 2).sum()) for p in used) / dof if dof else 0.0
    shared = float(np.mean([p.mean() ** 2 - within / len(p) for p in used]))
    return math.sqrt(within), math.sqrt(max(0.0, shared))
