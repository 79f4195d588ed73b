"""Forward + backward time and peak memory of every fusion operator on the CPU, relative to `sum`.

Usage: python bench/bench_fusion_ops.py [--shape 8 256 48 160] [--inputs 2] [--threads 1] [--repeats 3]
Two inputs of --shape (default: SMoE's batch of 8, 256 FPN channels, a 48 x 160 level); the loss is the
sum of the output. Memory and time method: bench_fusion_measure.py.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_fusion_measure import measure, table  # noqa: E402

from ablate.fusion import OPERATORS, build  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", type=int, nargs=4, default=[8, 256, 48, 160])
    parser.add_argument("--inputs", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    b, c, h, w = args.shape
    feats = [torch.randn(b, c, h, w, requires_grad=True) for _ in range(args.inputs)]
    names = ["sum"] + sorted(n for n in OPERATORS if n != "sum")
    rows, params = [], []
    for name in names:
        op = build(name, c, num_inputs=args.inputs, **({"size": (h, w)} if name == "plard" else {}))

        def step() -> None:
            op.zero_grad(set_to_none=True)
            for f in feats:
                f.grad = None
            op(feats).sum().backward()

        rows.append((name, *measure(step, args.repeats)))
        params.append(str(sum(p.numel() for p in op.parameters())))
        print(f"{name}: {rows[-1][1] * 1e3:.1f} ms, {rows[-1][2] / 2**20:.1f} MiB", file=sys.stderr, flush=True)
    print(
        f"fusion operators, {args.inputs} inputs of {args.shape}, CPU, {args.threads} thread(s), "
        f"median of {args.repeats}; torch {torch.__version__}"
    )
    print(table(rows, "sum", {"params": params}))


if __name__ == "__main__":
    main()
