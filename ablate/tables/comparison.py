"""One comparison of a race (:mod:`ablate.tables.racing`): row ``a`` against row ``b`` at the look where it was
decided or last tested, its verdict (:mod:`ablate.tables.verdicts`), the figures it rests on, and the words the
table's footer and figure give it.

Each comparison also reports P(A > B) over its paired seeds (Bouthillier et al. 2021, "Accounting for variance in
machine learning benchmarks", MLSys: a claim A > B wants the interval's lower bound above 0.5) with a Wilson score
interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, UNDECIDED, WORSE, Kernels, words

#: The test each verdict rests on (:class:`~ablate.tables.verdicts.PairedTests`' p-value), and how a line names it.
CLAIM_TESTS = {BETTER: "p_beyond", WORSE: "p_beyond", EQUIVALENT: "p_equiv", DIFFERENT: "p_diff", UNDECIDED: "p_diff"}
TEST_WORDS = {"p_beyond": "beyond ±δ", "p_equiv": "TOST within ±δ", "p_diff": "against 0"}
LEVEL = 0.95
#: What a comparison of fewer than 2 paired seeds says: no spread, so no test and no verdict.
NO_VERDICT = "no verdict"


@dataclass(frozen=True)
class Comparison:
    """Row ``a`` against row ``b`` (``a - b``) at the look where it was decided or last tested: its verdict
    (:mod:`ablate.tables.verdicts`: better, worse, equivalent, different, undecided), the paired figures, and the
    (1 - 2 ``level``) interval of the mean difference TOST reads (``lo``, ``hi``)."""

    a: str
    b: str
    why: str  # "reference" or "top vs second"
    look: int  # 1-based
    n: int  # paired seeds
    delta: float
    p: float
    level: float
    decided: bool  # the race gives it no more seeds
    p_ab: float  # P(A > B) over the paired seeds (ties count one half)
    p_ab_lo: float
    p_ab_hi: float
    kind: str = UNDECIDED
    lo: float = math.nan
    hi: float = math.nan
    rope: float | None = None
    frames: bool = False  # the interval adds the test frames' variance (ablate.tables.twolevel) to the seeds'
    sd: float = math.nan  # the seeds' standard deviation of the paired differences
    frames_se: float = 0.0  # the test frames' standard error of the mean difference (0: the seeds alone)
    kernels: Kernels = Kernels()  # another CPU's kernels' variance, where the table measured it

    def verdict(self) -> str:
        """The verdict in words, where it was reached, with the figures."""
        if self.n < 2:
            return f"{NO_VERDICT} (n = {self.n}: a test needs 2 paired seeds or more)"
        said = words(self.kind, self.rope)
        state = f"{said} at look {self.look}" if self.kind != UNDECIDED else said
        over = "t interval over seeds and test frames" if self.frames else "t interval"
        shown = self.rope is not None or self.frames
        share = f"{100 * (1 - 2 * self.level):.1f}%"
        interval = f"[{self.lo:+.2f}, {self.hi:+.2f}], the unadjusted {share} {over}; " if shown else ""
        spread = (
            f"seeds' sd {self.sd:.3g}"
            + (f", kernels' sd {self.kernels.per_seed:.3g}" if self.kernels.per_seed else "")
            + (f", another CPU's shift sd {self.kernels.shared:.3g}" if self.kernels.shared else "")
            + (f", frames' se {self.frames_se:.3g}" if self.frames else "")
        )
        return (
            f"{state} (n = {self.n}, Δ {self.delta:+.2f} {interval}{spread}; p = {self.p:.3g} {self.p_words()} "
            f"against {self.level:.4f}; P(A > B) = {self.p_ab:.2f} [{self.p_ab_lo:.2f}, {self.p_ab_hi:.2f}])"
        )

    def short(self) -> str:
        """The verdict in a few words, as the table's figure labels it."""
        return words(self.kind, self.rope) if self.n >= 2 else f"{NO_VERDICT} (n = {self.n})"

    def p_words(self) -> str:
        """What ``p`` is: the test the verdict rests on, adjusted over the table's comparisons at its look."""
        test = TEST_WORDS[CLAIM_TESTS.get(self.kind, "p_diff")] if self.rope is not None else "against 0"
        return f"({test}, adjusted over the look's comparisons)"
