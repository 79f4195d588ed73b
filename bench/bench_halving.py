"""Successive halving replayed on a table's full-budget tuning phase: what it would have cost and chosen.

Reads ``results/runs/<table>.trials.csv`` (or ``--records DIR``): each trial's validation value per epoch
(``val_curve``, recorded since trials keep it) from a phase that trained every trial to the full budget. For each
row, :func:`ablate.sweep.halving.replay` makes the choices successive halving would have made on those curves, which
is exact where a resumed trial trains as it did in one go (``tests/test_halving.py``). Prints, per row, the trial
full-budget selection chose and its objective, the trial halving chose and its objective, and the difference; then
the phase's CPU minutes both ways (halving's: each trial's seconds scaled by the epochs it would have trained), and
whether halving meets the bar for being the default (``docs/tuning.md#successive-halving``): at most half the CPU
minutes, and every row's choice the same or within the table's δ on validation.

Usage: ``python bench/bench_halving.py TABLE [--records DIR] [--eta 3] [--rungs 0.111111 0.333333 1] [--delta D]``;
the full-budget phases measured for ``docs/tuning.md`` are in ``bench/measured/halving`` (``--records`` that folder).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("table")
    parser.add_argument("--records", default=str(ROOT / "results"))
    parser.add_argument("--eta", type=int, default=3)
    parser.add_argument("--rungs", type=float, nargs="+", default=[0.111111, 0.333333, 1.0])
    parser.add_argument("--delta", type=float, default=None, help="δ on the objective's scale (default: the table's)")
    args = parser.parse_args()
    from ablate.jobs.rungs import read_curve
    from ablate.sweep.halving import Halving, best_until, full_choice, replay
    from ablate.tables.tuning import FULL, read_trials

    halving = Halving.from_config({"eta": args.eta, "rungs": args.rungs})
    assert halving is not None
    if args.delta is None:
        from omegaconf import OmegaConf

        from ablate.config import compose

        args.delta = OmegaConf.select(compose([f"experiment={args.table}"]), "table.rope.delta")
    trials = read_trials(args.records, args.table)
    trials = trials[trials["rung"].astype(float) == FULL]
    if trials.empty or not trials["val_curve"].notna().any():
        print(f"{args.table}: no full-budget trial with a recorded val_curve in {args.records}; tune it again")
        return 1
    print(f"{args.table}: {halving.describe()}; δ {args.delta}; CPU of the records: {trials['cpu'].iloc[0]}")
    full_min = halved_min = 0.0
    safe = True
    for row, sel in trials.groupby("row", sort=False):
        curves = {int(t): read_curve(c) for t, c in zip(sel["trial"], sel["val_curve"])}
        epochs = max(max(c) for c in curves.values() if c)
        got = replay(curves, halving, epochs)
        full = full_choice(curves, epochs)
        a, b = best_until(curves[full], epochs), best_until(curves[got.chosen], epochs)
        seconds = dict(zip(sel["trial"].astype(int), sel["seconds"].astype(float)))
        full_min += sum(seconds.values()) / 60
        ends = halving.rung_epochs(epochs)
        furthest = {k: ends[r] for r, alive in enumerate(got.rungs) for k in alive}
        halved_min += sum(seconds[k] * furthest[k] / epochs for k in curves) / 60
        same = full == got.chosen or (args.delta is not None and abs(a - b) <= args.delta)
        safe &= same
        print(
            f"  {row}: full budget chose trial {full} ({a:.4g}); halving trial {got.chosen} ({b:.4g}); "
            f"difference {b - a:+.4g}; trials per rung {[len(r) for r in got.rungs]}"
        )
    ratio = halved_min / full_min if full_min else float("nan")
    print(f"CPU min: full budget {full_min:.1f}, halving {halved_min:.1f} ({ratio:.0%})")
    print(f"default-safe on this table: {'yes' if safe and ratio <= 0.5 else 'no'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
