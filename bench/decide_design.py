"""Seeds and test frames together: what would decide each comparison a published table left open, for sizing the
next race's test split and seeds before it trains (:mod:`ablate.tables.decide`).

    PYTHONPATH=. python bench/decide_design.py [table ...] [--times 1,2,4,8,16]

Renders each table from a copy of its records (``results/`` is left as it is) and, for every comparison its race
left open, prints the seeds per row that would decide it with 80 % power at the spread observed and the level of
the race's last look, with the test split at each multiple of the frames its runs were tested on (the frames'
variance taken to fall as 1 / frames, the reading :mod:`ablate.tables.decide` states). A table whose records keep
no counts or detections per frame has no frames' term: its seeds do not depend on the test split.

Measured (Intel Xeon family 6 model 106, 30 s): DGFN Table II's two comparisons (100 test frames) need more than
1000 seeds per row at 100 frames; the camera SSD against DGFN 19 at 4x the frames and 12 at 8x, the DHI SSD 20 at 2x
and 10 at 4x. DGFN Table I's GFU against none needs 1000+ up to 8x and 954 at 16x: its seeds' sd (2.64) and a
difference near δ (+2.24 against 1.12) leave it open, whatever the test split. The BiFNet and ChiNet tables' open
comparisons turn on their seeds, not their 300 test frames.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
from pathlib import Path

import torch

import ablate.tables.decide as decide
from ablate.config import RESULTS, compose
from ablate.hardware import cpu
from ablate.tables import render_records
from ablate.tables.published import experiments


def open_comparisons(name: str, results: Path) -> list[tuple[str, str, float, float, float, float | None, float, int]]:
    """(a, b, Δ, sd, frames' se, δ, level, test frames) of each comparison ``name``'s race left open, as its footer
    prices them."""
    found = []
    original = decide.to_decide

    def record(c, plan, open_count, runs):  # type: ignore[no-untyped-def]
        todo = original(c, plan, open_count, runs)
        sd = math.hypot(c.sd, c.kernels_sd)
        frames = decide.test_frames(runs) if c.frames else 0
        found.append((c.a, c.b, c.delta, sd, c.frames_se, plan.rope, todo.level, frames))
        return todo

    decide.to_decide = record  # type: ignore[assignment]
    try:
        render_records(compose([f"experiment={name}"]), results, None, None)
    finally:
        decide.to_decide = original  # type: ignore[assignment]
    return list(dict.fromkeys(found))  # the footer and the CSV price each comparison: once each


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="*", help="published tables (default: every one)")
    parser.add_argument("--times", default="1,2,4,8,16", help="multiples of the test frames to price")
    args = parser.parse_args()
    times = [float(t) for t in args.times.split(",")]
    torch.set_num_threads(1)
    print(f"CPU: {cpu().model}; seeds per row for 80 % power at the race's last look's level")
    with tempfile.TemporaryDirectory(prefix="ablate-bench-design-") as scratch:
        results = Path(scratch) / "results"
        shutil.copytree(RESULTS, results)
        for name in args.tables or experiments():
            found = open_comparisons(name, results)
            if not found:
                continue
            print(f"\n{name}")
            for a, b, mean, sd, frames_se, rope, level, frames in found:
                head = f"  {a} vs {b}: Δ {mean:+.2f}, seeds' sd {sd:.3g}, frames' se {frames_se:.3g}"
                if not frames:
                    seeds = decide.seeds_to_decide(mean, sd, frames_se, rope, level)
                    print(f"{head}; no test frames kept: {seeds or f'{decide.MOST}+'} seeds")
                    continue
                cells = []
                for k in times:
                    seeds = decide.seeds_to_decide(mean, sd, frames_se / math.sqrt(k), rope, level)
                    cells.append(f"{k:g}x ({k * frames:.0f}): {seeds or f'{decide.MOST}+'}")
                print(f"{head} at {frames} frames; seeds per row at " + ", ".join(cells))


if __name__ == "__main__":
    main()
