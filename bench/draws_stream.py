"""Whether a table's verdicts hold for another stream of frame draws: the AP tables' frames' term
(:mod:`ablate.tables.twolevel`) comes from 1,000 draws of the test frames out of one fixed stream
(``ablate.tables.frames.AP_DRAWS_SEED``); another stream estimates the same variance with its own Monte Carlo error.

    PYTHONPATH=. python bench/draws_stream.py [table ...] [--streams 10]

Renders each table from a copy of its records (``results/`` is left as it is) once per stream, and prints per
comparison the verdict at the published stream, how many streams give the same verdict, and the range of the
interval's bounds over the streams. A table whose primary metric keeps counts per frame (ChiNet, BiFNet) takes the
jackknife, which draws nothing: its lines are the same on every stream.

Measured (Intel Xeon family 6 model 106, 20 streams, 2 min): every verdict of DGFN Tables I and II the same on all 20
(each undecided); the interval's bounds moved by at most 0.5 (Table I, Car moderate, [-9.17 to -8.67, +13.14 to
+13.64]) and 1.0 (Table II); the Table II follow-up's records keep no detections, so its intervals draw nothing.
The SMoE tables' records keep none either.
"""

from __future__ import annotations

import argparse
import functools
import re
import shutil
import tempfile
from collections import defaultdict
from pathlib import Path

import torch

import ablate.tables.twolevel as twolevel
from ablate.config import RESULTS, compose
from ablate.hardware import cpu
from ablate.tables import render_records
from ablate.tables.frames import AP_DRAWS_SEED, frame_draws
from ablate.tables.published import experiments

#: A verdict line of a table's footer: the comparison, the verdict, the mean difference and its interval.
VERDICT = re.compile(
    r"^(?P<pair>.+? vs .+?(?: \([^)]*\))?): (?P<verdict>[^(]+?) (?:at look \d+ )?\(n = \d+, Δ (?P<mean>[-+]\S+) "
    r"\[(?P<lo>[-+]\S+), (?P<hi>[-+]\S+)\]"
)
DETECTION_TABLES = ("dgfn_table1", "dgfn_table2", "dgfn_table2_followup")


def verdicts(name: str, results: Path, stream: int) -> dict[str, tuple[str, float, float]]:
    """Each comparison of ``name``'s table rendered with the frame draws of ``stream``: (verdict, lo, hi)."""
    twolevel.frame_draws = functools.partial(frame_draws, seed=stream)  # type: ignore[assignment]
    try:
        render_records(compose([f"experiment={name}"]), results, None, None)
    finally:
        twolevel.frame_draws = frame_draws  # type: ignore[assignment]
    out = {}
    for line in (results / f"{name}.md").read_text().splitlines():
        found = VERDICT.match(line)
        if found:
            out[found["pair"]] = (found["verdict"].strip(), float(found["lo"]), float(found["hi"]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="*", help="published tables (default: the detection tables, whose AP draws)")
    parser.add_argument("--streams", type=int, default=10, help="streams of draws, the published one first")
    args = parser.parse_args()
    names = args.tables or [n for n in experiments() if n in DETECTION_TABLES]
    streams = [AP_DRAWS_SEED, *(s for s in range(args.streams + 1) if s != AP_DRAWS_SEED)][: args.streams]
    torch.set_num_threads(1)
    print(f"CPU: {cpu().model}; {len(streams)} streams of frame draws: {streams}")
    with tempfile.TemporaryDirectory(prefix="ablate-bench-draws-") as scratch:
        results = Path(scratch) / "results"
        shutil.copytree(RESULTS, results)
        for name in names:
            seen: dict[str, list[tuple[str, float, float]]] = defaultdict(list)
            for stream in streams:
                for pair, found in verdicts(name, results, stream).items():
                    seen[pair].append(found)
            print(f"\n{name}: {len(seen)} comparisons")
            for pair, found in seen.items():
                first = found[0][0]
                same = sum(v == first for v, _, _ in found)
                los, his = [lo for _, lo, _ in found], [hi for _, _, hi in found]
                print(
                    f"  {pair}: {first} (stream {streams[0]}); the same on {same} of {len(found)} streams; "
                    f"interval's low {min(los):+.2f} to {max(los):+.2f}, high {min(his):+.2f} to {max(his):+.2f}"
                )
                for verdict in sorted({v for v, _, _ in found} - {first}):
                    print(f"    {verdict}: streams {[s for s, (v, _, _) in zip(streams, found) if v == verdict]}")


if __name__ == "__main__":
    main()
