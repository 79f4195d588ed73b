"""Seeds and test frames together: what would decide each comparison a published table left open, for sizing the
next race's test split and seeds before it trains (:mod:`ablate.tables.decide`).

    PYTHONPATH=. python bench/decide_design.py [table ...] [--times 1,2,4,8,16] [--scaling 10]

Renders each table from a copy of its records (``results/`` is left as it is) and, for every comparison its race
left open, prints the seeds per row that would decide it with 80 % power at the spread observed and the level of
the race's last look, with the test split at each multiple of the frames its runs were tested on (the frames'
variance taken to fall as 1 / frames, the reading :mod:`ablate.tables.decide` states). A table whose records keep
no counts or detections per frame has no frames' term: its seeds do not depend on the test split.

``--scaling N`` checks that reading on each comparison's own frames: the frames' variance on N random halves of the
test split against the whole's (1 / frames predicts 2x).

Measured (Intel Xeon family 6 model 106, 30 s): DGFN Table II's two comparisons (100 test frames) need more than
1000 seeds per row at 100 frames; the camera SSD against DGFN 19 at 4x the frames and 12 at 8x, the DHI SSD 20 at 2x
and 10 at 4x. DGFN Table I's GFU against none needs 1000+ up to 8x and 954 at 16x: its seeds' sd (2.64) and a
difference near δ (+2.24 against 1.12) leave it open, whatever the test split. The BiFNet and ChiNet tables' open
comparisons turn on their seeds, not their 300 test frames.

The reading checked (``--scaling 10``, 3 min): on ten random halves of the test split the counts tables' frames'
variance is 1.7-2.1x the whole's (ChiNet Tables II and IV, BiFNet IV-VI; 2.0 or near it on 9 of 11 comparisons), as
1 / frames says; the AP tables' 1.2-1.9x (DGFN Table I 1.18, Table II 1.61 and 1.94). Either an 11-point AP's
bootstrap on few frames reads low, or its variance falls slower than 1 / frames; in the second case the AP tables
need more frames than estimated.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

import ablate.tables.decide as decide
from ablate.config import RESULTS, compose
from ablate.hardware import cpu
from ablate.tables import render_records
from ablate.tables.frames import read_detections, read_frames, verdict_metric
from ablate.tables.published import experiments
from ablate.tables.records import read_records
from ablate.tables.spec import table_spec
from ablate.tables.twolevel import frames_variance


def open_comparisons(
    name: str, results: Path
) -> list[tuple[str, str, float, float, float, float | None, float, int, float]]:
    """(a, b, Δ, sd, frames' se, δ, level, test frames, another CPU's shared shift) of each comparison ``name``'s
    race left open, as its footer prices them."""
    found = []
    original = decide.to_decide

    def record(c, plan, open_count, runs, frames_now=0):  # type: ignore[no-untyped-def]
        todo = original(c, plan, open_count, runs, frames_now)
        sd = math.hypot(c.sd, c.kernels.per_seed)
        frames = frames_now if c.frames else 0
        found.append((c.a, c.b, c.delta, sd, c.frames_se, plan.rope, todo.level, frames, c.kernels.shared))
        return todo

    decide.to_decide = record  # type: ignore[assignment]
    try:
        render_records(compose([f"experiment={name}"]), results, None, None)
    finally:
        decide.to_decide = original  # type: ignore[assignment]
    return list(dict.fromkeys(found))  # the footer and the CSV price each comparison: once each


def halves(name: str, a: str, b: str, draws: int) -> float:
    """The frames' variance of ``a - b`` (their shared seeds) on ``draws`` random halves of ``name``'s test split,
    over the whole split's: 2 where the variance falls as 1 / frames."""
    spec = table_spec(compose([f"experiment={name}"]))
    primary, condition = verdict_metric(spec)
    counts, detections = read_frames(RESULTS, name), read_detections(RESULTS, name)
    kept = counts if len(counts) else detections
    runs = read_records(RESULTS / "runs" / f"{name}.csv")
    seeds = sorted(set(runs.loc[runs["row"] == a, "seed"]) & set(runs.loc[runs["row"] == b, "seed"]))

    def variance(frames: np.ndarray) -> float:
        sub = kept[kept["frame"].isin(frames)]
        term = frames_variance(sub if len(counts) else None, primary, condition, None if len(counts) else sub)
        return term(a, b, seeds) if term is not None else math.nan

    every = np.array(sorted(kept["frame"].astype(str).unique()))
    rng = np.random.default_rng(0)
    half = [variance(rng.permutation(every)[: len(every) // 2]) for _ in range(draws)]
    return float(np.mean(half) / variance(every))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="*", help="published tables (default: every one)")
    parser.add_argument("--times", default="1,2,4,8,16", help="multiples of the test frames to price")
    parser.add_argument("--scaling", type=int, default=0, help="random halves of the test split to check 1 / frames on")
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
            for a, b, mean, sd, frames_se, rope, level, frames, shared in found:
                head = f"  {a} vs {b}: Δ {mean:+.2f}, seeds' sd {sd:.3g}, frames' se {frames_se:.3g}"
                head += f", shared kernels' sd {shared:.3g}" if shared else ""
                if not frames:
                    seeds = decide.seeds_to_decide(mean, sd, math.hypot(frames_se, shared), rope, level)
                    print(f"{head}; no test frames kept: {seeds or f'{decide.MOST}+'} seeds")
                    continue
                cells = []
                for k in times:
                    seeds = decide.seeds_to_decide(mean, sd, math.hypot(frames_se / math.sqrt(k), shared), rope, level)
                    cells.append(f"{k:g}x ({k * frames:.0f}): {seeds or f'{decide.MOST}+'}")
                print(f"{head} at {frames} frames; seeds per row at " + ", ".join(cells))
                if args.scaling:
                    print(
                        f"    frames' variance on half the frames: {halves(name, a, b, args.scaling):.2f}x the whole's"
                    )


if __name__ == "__main__":
    main()
