"""Where one training step of each task family's real model spends its time, by torch.profiler: the top operators
by self CPU time, and the share that is not tensor compute (Python between operators: loops in losses, matching,
per-object work).

    PYTHONPATH=. python bench/profile_step.py [--families chinet,dgfn] [--top 12] [--threads 1]

The families and their batches are bench_precision.py's (the cpu scale, real generated frames, fp32). One step
is profiled after one warm-up step. "Outside operators" is the step's wall time less the operators' self time: the
host-side Python the step runs between tensor operations.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_precision import FAMILIES, Variant, build  # noqa: E402

from ablate.hardware import cpu  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--top", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"CPU: {cpu().model} ({cpu().isa}); {args.threads} thread(s); torch {torch.__version__}")
    here = os.getcwd()
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        try:
            for family in args.families.split(","):
                task, batch, cfg = build(family)
                step = Variant("fp32", task, batch)
                step.train_step()
                with profile(activities=[ProfilerActivity.CPU]) as prof:
                    t0 = time.perf_counter()
                    step.train_step()
                    wall = time.perf_counter() - t0
                events = prof.key_averages()
                self_total = sum(e.self_cpu_time_total for e in events) / 1e6
                print(
                    f"\n{family}: one training step {wall:.3f} s; operators' self time {self_total:.3f} s; "
                    f"outside operators {max(wall - self_total, 0):.3f} s "
                    f"({100 * max(wall - self_total, 0) / wall:.0f} %)"
                )
                print(events.table(sort_by="self_cpu_time_total", row_limit=args.top, max_name_column_width=48))
        finally:
            os.chdir(here)


if __name__ == "__main__":
    main()
