"""How much of another CPU's kernels' variance a table's verdicts bear, where the table has not measured it.

A seed trained on another CPU's kernels lands elsewhere (docs/verdicts.md): where a table measured how far
(``table.kernels_sd``, ``bench/kernel_spread.py``), its tests add that variance to each seed's paired difference,
``se = sqrt((s² + k²) / n + f²)`` (:func:`ablate.tables.verdicts.paired_tests`). Where it did not, its verdicts
hold for its records' CPU alone. :func:`kernels_margin` says how far they would hold elsewhere: the largest ``k`` at
which the race, replayed on the same records with ``k`` added, reaches every claim it reached without (the same
verdict of each comparison that had one; at a later look where the records have its seeds), and the comparison
that changes first beyond it. Wider intervals only take claims away, so the claims that hold at ``k`` hold below it,
and a bisection finds the edge. A table whose measured ``k`` (on another table of its family, or later on its own)
falls below this margin keeps its verdicts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from ablate.tables.racing import RaceState
from ablate.tables.verdicts import UNDECIDED

#: The bisection stops where the edge is known to this share of itself.
PRECISION = 0.005
#: A margin past this many times the largest claimed |Δ| is reported as unbounded (no claim would change).
UNBOUNDED = 1000.0


@dataclass(frozen=True)
class Margin:
    """The largest kernels' sd every claim bears (``sd``, a lower bound to :data:`PRECISION`; ``math.inf`` where no
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
            f"Every claim would still hold with another CPU's kernels adding an sd of up to {floor_2(self.sd):g} "
            f"{label} to each seed's paired difference; beyond it {names.get(self.a, self.a)} vs "
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
    """The largest kernels' sd at which ``replay_at(sd)`` (the table's race replayed with that sd added to each seed's
    paired difference) reaches every claim ``replay_at(0)`` reached; None where it reached none."""
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
