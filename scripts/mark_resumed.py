"""Add the ``resumed_step`` column to a table's records made before the column, from the runs' own tags read where
the store is no longer at hand (the table's notes at the time it was raced).

    python scripts/mark_resumed.py dgfn_table2_followup dgfn_clean:0:19 dgfn_clean:1:19 dgfn_clean:2:113 ...

Each ``row:seed:step`` names a run resumed from a checkpoint at that training step; every other run of the table
is marked uninterrupted (empty). Records that already carry the column are left as they are; the records are
rewritten in their own column order (:func:`ablate.tables.records.to_records`), every other value unchanged.
"""

from __future__ import annotations

import argparse
import sys

from ablate.tables.records import read_records, records_path, to_records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("table")
    parser.add_argument("resumed", nargs="*", help="row:seed:step of each resumed run")
    parser.add_argument("--results", default="results")
    args = parser.parse_args(argv)
    path = records_path(args.results, args.table)
    if not path.is_file():
        print(f"error: no records at {path}", file=sys.stderr)
        return 2
    runs = read_records(path)
    if "resumed_step" in runs:
        print(f"{path} already has resumed_step: left as it is")
        return 0
    runs = runs.assign(resumed_step="").copy()
    for spec in args.resumed:
        try:
            row, seed, step = spec.split(":")
            int(step)
        except ValueError:
            print(f"error: {spec!r} is not row:seed:step", file=sys.stderr)
            return 2
        hit = (runs["row"] == row) & (runs["seed"].astype(str) == seed)
        if not hit.any():
            print(f"error: {path} has no run of row {row} seed {seed}", file=sys.stderr)
            return 2
        runs.loc[hit, "resumed_step"] = step
    to_records(runs, args.table).to_csv(path, index=False, lineterminator="\n")
    print(f"{path}: {len(args.resumed)} of {len(runs)} runs marked resumed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
