"""What keeping decoded frames between epochs (``data.memo_gb``, ablate.data.memo) saves: one paper row per task
family at the cpu scale, its training split read twice in the order a job reads it, without the memo and with it;
seconds per epoch and the memo's size. 1 thread, as a job at the cpu scale; the data generated on first use.

    PYTHONPATH=. python bench/bench_memo.py [experiment:row ...]

Measured (AMD EPYC family 25 model 17, fp32, 1 thread; 900 training frames), seconds of a second epoch's reading
without the memo / with it, and the GiB kept: BiFNet 4.9 / 0.32 (1.33), SMoE 6.0 / 0.27 (1.26), DGFN 3.5 / 0.27
(1.12), ChiNet 3.0 / 0.22 (1.07). A whole BiFNet Table IV job (``python -m ablate experiment=bifnet_table4
row=bifnet_dst_sum seed=0``: its two experts, 6 epochs each, then the fused network, 3), two side by side, with
``data.memo_gb=0`` and ``2``: every metric the same; 7 min 36 s / 6 min 46 s, 422 / 386 CPU s, peak RSS 1.4 / 3.0 GB.
An SMoE Table 1 job alike (``experiment=smoe_table1 row=smoe_sum seed=0``: two experts of 10 epochs, then stage 2,
4): every metric the same; 24 min 21 s / 22 min 05 s, 1374 / 1258 CPU s, peak RSS 4.0 / 5.3 GB.
"""

from __future__ import annotations

import argparse
import time

import torch
from hydra.utils import instantiate

from ablate.config import compose
from ablate.hardware import cpu

ROWS = ["bifnet_table4:bifnet_dst_sum", "smoe_table1:smoe_sum", "dgfn_table2:dgfn", "chinet_table2:chinet"]


def epochs(table: str, row: str, memo_gb: float, n: int = 2) -> tuple[list[float], float]:
    """Seconds of each of ``n`` passes over ``row``'s training loader, and the GiB its memo holds after them."""
    cfg = compose([f"experiment={table}", f"row={row}", f"data.memo_gb={memo_gb}"])
    dm = instantiate(cfg.data)
    loader = dm.train_dataloader()
    times = []
    for _ in range(n):
        start = time.perf_counter()
        for _batch in loader:
            pass
        times.append(time.perf_counter() - start)
    memo = dm.datasets["train"].memo
    return times, (memo.nbytes / 2**30 if memo is not None else 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rows", nargs="*", default=ROWS, help="experiment:row (default: one row per family)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"CPU: {cpu().model} ({cpu().isa}), 1 thread")
    print("| row | epoch 1, s | epoch 2 without the memo, s | epoch 2 with it, s | kept, GiB |")
    print("|:--|--:|--:|--:|--:|")
    for spec in args.rows:
        table, row = spec.split(":")
        plain, _ = epochs(table, row, 0)
        kept, gib = epochs(table, row, 2)
        print(f"| {spec} | {plain[0]:.1f} | {plain[1]:.1f} | {kept[1]:.2f} | {gib:.2f} |", flush=True)


if __name__ == "__main__":
    main()
