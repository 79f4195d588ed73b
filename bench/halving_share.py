"""What successive halving can save in each tuned table's phase, before any trial trains: from the table's N
(``table.tune_trials``) and each row's recipe epochs (a single-modal row's trial trains its expert, on the expert's own
epochs, :func:`ablate.jobs.experts.expert_config`; a fused row the stage-2 ``trainer.max_epochs``), the share of the full-budget phase's
epochs that halving trains (:meth:`ablate.sweep.halving.Halving.cost` at whole epochs). A rung rounds to whole
epochs, so a short recipe halves little: the cost bar of ``docs/tuning.md#successive-halving`` (at most half) is
out of reach where the share printed is above 50%, whatever the curves. The table's share weighs its rows by
epochs (every epoch of a row alike: a guide, not a CPU figure; ``bench/bench_halving.py`` gives those).

Usage: ``python bench/halving_share.py [TABLE ...] [--eta 3] [--rungs 0.111111 0.333333 1]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="*", help="experiment names (default: every table with a tune_trials)")
    parser.add_argument("--eta", type=int, default=3)
    parser.add_argument("--rungs", type=float, nargs="+", default=[0.111111, 0.333333, 1.0])
    args = parser.parse_args()
    from omegaconf import OmegaConf

    from ablate.config import compose
    from ablate.jobs.experts import expert_config
    from ablate.sweep.halving import Halving

    halving = Halving.from_config({"eta": args.eta, "rungs": args.rungs})
    assert halving is not None
    names = args.tables or sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
    print(halving.describe())
    for name in names:
        table = compose([f"experiment={name}"]).table
        trials = table.get("tune_trials")
        if not trials or table.get("untuned"):
            print(f"{name}: raced on the recipe, untuned")
            continue
        spent = full = 0.0
        parts = []
        for row in (str(r.row) for r in table.rows if not r.get("paper_only")):
            cfg = compose([f"experiment={name}", f"row={row}"])
            if OmegaConf.select(cfg, "stage.name") == "single":  # a single-modal row's trial trains its expert
                cfg = expert_config(cfg, str(cfg.stage.modality))
            epochs = int(cfg.trainer.max_epochs)
            share = halving.cost(int(trials), epochs) / int(trials)
            spent, full = spent + share * epochs, full + epochs
            parts.append(f"{row} {epochs} ep {halving.rung_epochs(epochs)} {share:.0%}")
        print(f"{name}: N = {trials}; {'; '.join(parts)}; the table {spent / full:.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
