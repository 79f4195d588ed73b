"""Forward + backward time and peak memory of every fusion stage on the CPU, relative to `single`.

Usage: python bench/bench_fusion_stages.py [--op smoe] [--batch 2] [--size 128 416] [--depth 18] [--width 0.5]
       [--fpn 64] [--threads 1] [--repeats 3]
Modalities rgb (3 channels) and dense_depth (1 channel); `single` uses rgb. The head is a small shared
3x3 conv per FPN level (classes + box maps, as an SSD/YOLACT prediction layer); the loss is the sum of all
maps. Also prints parameters and MACs (FusionModel.macs, batch 1). Method: bench_fusion_measure.py.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_fusion_measure import measure, table  # noqa: E402

from ablate.fusion import STAGES, FusionModel, build  # noqa: E402

MODALITIES = {"rgb": 3, "dense_depth": 1}


class SharedHead(nn.Module):
    """One 3x3 conv shared by all levels, giving class and box maps per level."""

    def __init__(self, in_channels: int, num_levels: int, classes: int = 3) -> None:
        super().__init__()
        self.classes = classes
        self.out_channels = {"cls": [classes] * num_levels, "box": [4] * num_levels}
        self.conv = nn.Conv2d(in_channels, classes + 4, 3, padding=1)

    def forward(self, levels: list[torch.Tensor]) -> dict[str, list[torch.Tensor]]:
        maps = [self.conv(p) for p in levels]
        return {"cls": [m[:, : self.classes] for m in maps], "box": [m[:, self.classes :] for m in maps]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--op", default="smoe")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--size", type=int, nargs=2, default=[128, 416])
    parser.add_argument("--depth", type=int, default=18)
    parser.add_argument("--width", type=float, default=0.5)
    parser.add_argument("--fpn", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    h, w = args.size
    x = {m: torch.randn(args.batch, c, h, w) for m, c in MODALITIES.items()}
    rows, params, macs = [], [], []
    stages = ["single"] + [s for s in args.stages if s != "single"]
    for stage in stages:
        model = FusionModel(
            stage=stage,
            modalities=MODALITIES,
            head=SharedHead,
            single="rgb",
            fusion=functools.partial(build, name=args.op),
            fpn_channels=args.fpn,
            backbone={"depth": args.depth, "width": args.width},
        )

        def step() -> None:
            model.zero_grad(set_to_none=True)
            sum(t.sum() for v in model(x).values() for t in v).backward()

        rows.append((stage, *measure(step, args.repeats)))
        params.append(f"{model.num_parameters():,}")
        macs.append(f"{model.macs({m: (c, h, w) for m, c in MODALITIES.items()}) / 1e9:.3f}")
        print(f"{stage}: {rows[-1][1] * 1e3:.1f} ms, {rows[-1][2] / 2**20:.1f} MiB", file=sys.stderr, flush=True)
    print(
        f"fusion stages with `{args.op}`, ResNet-{args.depth} x{args.width}, FPN {args.fpn}, batch {args.batch} of "
        f"{h}x{w}, CPU, {args.threads} thread(s), median of {args.repeats}; torch {torch.__version__}"
    )
    print(table(rows, "single", {"params": params, "GMACs (B=1)": macs}))


if __name__ == "__main__":
    main()
