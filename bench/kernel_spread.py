"""How far another CPU's kernels move each seed's result, against the seeds' own spread.

    python bench/kernel_spread.py experiment=bifnet_table4 rows=bifnet_dst_sum,bifnet_dst_cbf seeds=0,1,2 \
        [kernels=avx2] [out=kernel_spread.json] [store=DIR]

Reruns each (row, seed) of a published table here, on the table's configs and seeds (its tuned config where it was
tuned: :mod:`ablate.analysis.reproduce`), with torch's and oneDNN's kernels held to a lower instruction set
(``ATEN_CPU_CAPABILITY``, ``ONEDNN_MAX_CPU_ISA``: ``kernels=avx2`` runs the AVX2 EPYC's kernels on any newer CPU),
and prints, per seed, the published value, the rerun's and the shift; per row, the seeds' standard deviation in the
records and the shifts' root mean square; and, per pair of rows, the same for their paired difference, the figure a
verdict reads. The JSON keeps every number. The CPU and the kernels are printed first. ``store=DIR`` keeps one
store for every rerun, so that each seed's experts train once for all the rows that start from them (seeds inner,
rows outer: list the fused rows first). Last, every pair's shift pooled (a table's ``kernels_sd``) and every rerun's
(root mean square, the rows' seeds together) with the seeds it came from: a table's ``kernels_run``
(docs/verdicts.md), which ``make run``'s comparison and ``--reproduce`` add to the prediction interval of a run made
with other numerics. ``from=FILE[,FILE...]`` prints the same from JSONs it
wrote, rerunning nothing, and pools several (each another draw of the kernels)::

    python bench/kernel_spread.py from=bench/measured/kernel_spread_bifnet_table4.json,bench/measured/kernel_spread_bifnet_table4_xeon106.json

``kernel_spread_bifnet_table4_xeon106.json`` holds ``make run``'s runs on an Intel Xeon family 6 model 106 (its own
kernels, the published config hashes), ``kernel_spread_bifnet_table5_xeon106.json`` this script's reruns there
(``kernels=default``): another CPU's real shift beside the AVX2 kernels held on the CPU that made the records.

A bf16 table (ChiNet's, DGFN's: records of the EPYC model 17, AVX-512 BF16) has no cheap second draw: held to
``kernels=avx512`` there (oneDNN's AVX512_CORE, bf16 without its instructions, as a Xeon model 106 runs it) a ChiNet
Table III job took 8.75 s a step, about 33 min, against 6.7 min on the CPU's own kernels (2026-12-07): 3.3 h for
one table's 3 seeds of 2 rows, and ``kernels=avx2`` is about 30x slower still. Its second draw is another CPU with
native bf16 (a Xeon with AMX) running ``kernels=default``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ablate.tables.margin import shift_parts

#: kernels=NAME -> the environment that holds torch's and oneDNN's kernels to it.
KERNELS = {
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"},
    "avx512": {"ATEN_CPU_CAPABILITY": "avx512", "ONEDNN_MAX_CPU_ISA": "AVX512_CORE"},
    "default": {},
}


def main(argv: list[str]) -> int:
    own = ("rows", "seeds", "kernels", "out", "store", "from")
    opts = dict(a.split("=", 1) for a in argv if "=" in a and a.split("=", 1)[0] in own)
    rest = [a for a in argv if a.split("=", 1)[0] not in own]
    if "from" in opts:
        pairs: list[np.ndarray] = []
        shifts: list[float] = []
        seeds_in_all = 0
        for name in opts["from"].split(","):
            kept = json.loads(Path(name).read_text())
            print(f"CPU: {kept['cpu']} ({kept['isa']}); kernels={kept['kernels']}; table {kept['table']} ({name})")
            runs = {r: {int(s): (v["published"], v["rerun"]) for s, v in by.items()} for r, by in kept["runs"].items()}
            paired, every, seeds_here = summarise(kept["metric"], runs, kept["seeds_sd"])
            pairs, shifts, seeds_in_all = pairs + paired, shifts + every, seeds_in_all + seeds_here
        if "," in opts["from"]:  # each file's reruns are another draw of the kernels: pooled
            (sd, cpu), run = shift_parts(pairs), float(np.sqrt(np.mean(np.square(shifts))))
            print(
                f"pooled over the files: paired differences' shift, per seed {sd:.4f} and shared {cpu:.4f} "
                f"(table.kernels_sd: {sd:.3f}, table.kernels_cpu: {cpu:.3f}); every rerun's {run:.4f} over "
                f"{seeds_in_all} seeds (table.kernels_run: {{sd: {run:.3f}, seeds: {seeds_in_all}}})"
            )
        return 0
    kernels = opts.get("kernels", "avx2")
    os.environ.update(KERNELS[kernels])  # the reruns are subprocesses: they inherit it

    from ablate import hardware
    from ablate.analysis.reproduce import reproduce
    from ablate.config import compose
    from ablate.tables import table_spec

    machine = hardware.cpu()
    cfg = compose(rest)
    table = table_spec(cfg)
    rows, seeds = opts["rows"].split(","), [int(s) for s in opts.get("seeds", "0,1,2").split(",")]
    print(f"CPU: {machine.model} ({machine.isa}); kernels={kernels} {KERNELS[kernels]}; table {table.name}")
    found: dict[str, dict[int, tuple[float, float]]] = {}
    spread: dict[str, float] = {}
    for row in rows:
        found[row] = {}
        for seed in seeds:
            start = time.monotonic()
            keep = Path(opts["store"]) if "store" in opts else None  # one store: each seed's experts trained once
            outcome = reproduce(cfg, [*rest, f"row={row}", f"seed={seed}"], keep=keep)
            found[row][seed] = (float(outcome.recorded or math.nan), outcome.value)
            spread[row] = float(np.std(outcome.values, ddof=1))
            print(
                f"  {row} seed {seed}: published {outcome.recorded:.4f}, rerun {outcome.value:.4f}, "
                f"shift {outcome.value - (outcome.recorded or math.nan):+.4f} ({time.monotonic() - start:.0f} s)",
                flush=True,
            )
    summarise(str(table.primary), found, spread)
    if "out" in opts:
        payload = {
            "cpu": machine.model,
            "isa": machine.isa,
            "kernels": kernels,
            "table": str(table.name),
            "metric": str(table.primary),
            "seeds_sd": spread,
            "runs": {r: {str(s): {"published": v[0], "rerun": v[1]} for s, v in found[r].items()} for r in rows},
        }
        Path(opts["out"]).write_text(json.dumps(payload, indent=1) + "\n")
    return 0


def summarise(
    metric: str, found: dict[str, dict[int, tuple[float, float]]], spread: dict[str, float]
) -> tuple[list[np.ndarray], list[float], int]:
    """Per row, the seeds' sd against the shifts' root mean square; per pair of rows, their paired difference's,
    then every pair's pooled and split into the seeds' own part and the part they share (a table's ``kernels_sd``
    and ``kernels_cpu``: :func:`ablate.tables.margin.shift_parts`); then every rerun's shift pooled (its
    ``kernels_run``). Returns each pair's shifts, the reruns' and the number of seeds."""
    paired: list[np.ndarray] = []
    rows = list(found)
    print(f"{metric}: per row, the seeds' sd in the records against the kernels' shift (root mean square)")
    for row in rows:
        shifts = np.array([new - old for old, new in found[row].values()])
        print(f"  {row}: seeds' sd {spread[row]:.4f}, kernels' shift rms {np.sqrt(np.mean(shifts**2)):.4f}")
    for i, a in enumerate(rows):
        for b in rows[i + 1 :]:
            seeds = sorted(set(found[a]) & set(found[b]))
            old = np.array([found[a][s][0] - found[b][s][0] for s in seeds])
            new = np.array([found[a][s][1] - found[b][s][1] for s in seeds])
            paired.append(new - old)
            print(
                f"  {a} - {b}: published {old.mean():+.4f} (paired sd {old.std(ddof=1):.4f}), rerun "
                f"{new.mean():+.4f} (paired sd {new.std(ddof=1):.4f}); the difference's shift rms "
                f"{np.sqrt(np.mean((new - old) ** 2)):.4f}"
            )
    if paired:
        pooled = float(np.sqrt(np.mean(np.square(np.concatenate(paired)))))
        sd, cpu = shift_parts(paired)
        print(
            f"every pair: the difference's shift rms {pooled:.4f}; per seed {sd:.4f}, shared by the seeds {cpu:.4f} "
            f"(table.kernels_sd: {sd:.3f}, table.kernels_cpu: {cpu:.3f})"
        )
    every = np.array([new - old for row in rows for old, new in found[row].values()])
    rms, seeds = float(np.sqrt(np.mean(every**2))), len({s for row in rows for s in found[row]})
    print(
        f"every rerun: shift rms {rms:.4f} over {len(every)} reruns of {seeds} seeds (a seed's rows share its experts "
        f"and move together: table.kernels_run: {{sd: {rms:.3f}, seeds: {seeds}}})"
    )
    return paired, list(every), seeds


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
