"""How long ``python -m ablate.report`` takes: each published table rendered from a copy of its records (``results/``
is left as it is), timed without and with the footer's fingerprint check (which recomputes one run per row and
commit where the code its runs build changed since), on this machine's CPU, 1 thread.

    PYTHONPATH=. python bench/bench_report.py [table ...]

Measured (AMD EPYC family 25 model 17, 2 cores, the 13 published tables, ``python -m ablate.report``): 3 min 25 s,
then 1 min 35 s once the counts were split by run in one pass (``ablate.tables.frames.counts_by_run``) and each
file's imports parsed once a process (``ablate.tables.provenance``), then 56 s once the counts per frame beside the
runs were shared instead of deep-copied into every column read (``ablate.tables.kept``): BiFNet Table IV renders in
2.1 s instead of 11.4. Every table byte for byte the same.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch

from ablate.analysis.reproduce import recorded_config
from ablate.config import RESULTS, compose
from ablate.hardware import cpu
from ablate.jobs.fingerprint import compute
from ablate.tables import render_records
from ablate.tables.published import experiments


def timed(name: str, results: Path, check: bool) -> float:
    """Seconds to render ``name``'s table under ``results`` from its records, with or without the fingerprint
    check."""
    base = [f"experiment={name}"]
    start = time.perf_counter()
    render_records(
        compose(base),
        results,
        compute if check else None,
        (lambda runs: recorded_config(runs, base)) if check else None,
    )
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", nargs="*", help="published tables (default: all)")
    names = parser.parse_args().tables or experiments()
    torch.set_num_threads(1)
    print(f"CPU: {cpu().model} ({cpu().isa}), 1 thread; {len(names)} table(s) rendered from a copy of their records")
    print(f"{'table':<24} {'render (s)':>11} {'with fingerprint check (s)':>27}")
    totals = [0.0, 0.0]
    with tempfile.TemporaryDirectory(prefix="ablate-bench-report-") as scratch:
        results = Path(scratch) / "results"
        shutil.copytree(RESULTS, results)
        for name in names:
            plain, checked = timed(name, results, False), timed(name, results, True)
            totals = [totals[0] + plain, totals[1] + checked]
            print(f"{name:<24} {plain:>11.1f} {checked:>27.1f}")
    print(f"{'all':<24} {totals[0]:>11.1f} {totals[1]:>27.1f}")


if __name__ == "__main__":
    sys.exit(main())
