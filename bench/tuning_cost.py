"""What a tuning phase costs per table at the cpu scale on this machine, beside the race's first look after it.

For each experiment (or those named), the sweep's plan (:mod:`ablate.sweep.plan`) with ``tune=lr_wd`` and
``table.tune.trials=N``: every trial and every job of the first look, each estimated from its recipe's steps at a
step time measured here (``plan.measure_s`` seconds of timing per table, the first row and expert whatever the time),
then scheduled on the sweep's workers. Prints, per table, the rows, the estimated wall time of the trials and of the
first look, and the N that fits the regeneration's budget of about 3 h for tuning plus racing (the first look's
wall time counted three times over: later looks add seeds where rows are undecided). In a table on experts each
trial index first trains every expert once (the experts' own trials, side by side), then stage 2 of every fused row
on the chosen experts (copied from the chosen trials, not trained again); a single-modal row is its expert.

Usage: ``python bench/tuning_cost.py [--trials 8] [--budget-h 3] [experiment ...]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--budget-h", type=float, default=3.0)
    parser.add_argument("--measure-s", type=float, default=20.0)
    parser.add_argument("experiments", nargs="*")
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    from ablate import hardware
    from ablate.sweep.plan import estimate, items, wall_seconds
    from tests.test_progress import sweep_config

    machine = hardware.cpu()
    print(f"CPU: {machine.model} ({machine.isa}); N = {args.trials} trials per row; 2 jobs at a time")
    names = args.experiments or sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
    print(f"{'table':24} {'rows':>4} {'trials (h)':>10} {'first look (h)':>14} {'N within budget':>15}")
    for name in names:
        plain = items(sweep_config(f"experiment={name}"))
        estimate(plain, args.measure_s)
        look = wall_seconds(plain, 2)
        rows = len({i.key for i in plain if not i.key.startswith("expert")})
        if look is None:
            print(f"{name:24} {rows:>4} {'—':>10} {'—':>14} {'—':>15}")
            continue
        experts = wall_seconds(list({i.key: i for i in plain if i.key.startswith("expert")}.values()), 2) or 0.0
        per_trial = _trial_seconds(plain) + experts  # the experts' trials, then stage 2's, per trial index
        trials = args.trials * per_trial
        left = args.budget_h * 3600 - 3 * look
        fits = max(0, int(left // per_trial)) if per_trial > 0 else 0
        print(f"{name:24} {rows:>4} {trials / 3600:>10.2f} {look / 3600:>14.2f} {fits:>15}")


def _trial_seconds(plan: list) -> float:
    """One trial index's wall time on two workers: every row's job once (its test counted: an overestimate)."""
    from ablate.sweep.plan import Item, wall_seconds

    seen: dict[str, Item] = {}
    for item in plan:
        single = item.config.get("experts") and item.config.stage.name == "single"  # its expert's trials tune it
        if not item.key.startswith("expert") and not single and item.key not in seen:
            seen[item.key] = item
    return wall_seconds(list(seen.values()), 2) or 0.0


if __name__ == "__main__":
    main()
