"""Stage-2 training step (SMoE §4.3: the fusion network on frozen experts) with and without the experts' feature
cache (ablate.jobs.experts.FeatureCache), at the cpu scale: the default job with fusion=smoe (RGB + DDM fused at P3..P7,
ResNet-18 x0.25 + FPN 64 per expert, YOLACT head), batch 8 at 128x416. Prints milliseconds per training step
(forward, SMoE eq. 7 loss, backward, Adam step; median over steps) and the cache's memory.

    PYTHONPATH=. python bench/bench_stage2.py [--steps 20] [--batches 4] [--objects 6] [--threads 1]

The variants (no cache; an empty cache that the step fills; the cache filled by one pass beforehand) step the
same model on the same batches, interleaved in one process (the machine is shared). Synthetic inputs and targets:
the experts' cost does not depend on them.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from ablate.jobs.experts import FeatureCache, expert_config, feature_cache

CONF = Path(__file__).resolve().parents[1] / "conf"
FIT_SHARE = 0.8  # train + val frames of the generated data (its split is 60/20/20): what one fit caches


def synthetic_batch(frames: list[str], size: tuple[int, int], n_objects: int, gen: torch.Generator) -> dict:
    h, w = size
    instances = []
    for _ in frames:
        bh = torch.randint(10, 60, (n_objects,), generator=gen)
        bw = (bh * (1 + torch.rand(n_objects, generator=gen))).long()
        y1 = (torch.rand(n_objects, generator=gen) * (h - bh)).long()
        x1 = (torch.rand(n_objects, generator=gen) * (w - bw)).long()
        boxes = torch.stack([x1, y1, x1 + bw, y1 + bh], 1).float()
        masks = torch.zeros(n_objects, h, w, dtype=torch.bool)
        for i, (a, b, c, d) in enumerate(boxes.long().tolist()):
            masks[i, b:d, a:c] = True
        instances.append({"boxes": boxes, "labels": torch.randint(0, 2, (n_objects,), generator=gen), "masks": masks})
    n = len(frames)
    return {
        "rgb": torch.rand(n, 3, h, w, generator=gen),
        "ddm_jet": torch.rand(n, 3, h, w, generator=gen),
        "instances": instances,
        "ignore": torch.zeros(n, h, w, dtype=torch.bool),
        "frame": frames,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="timed steps per variant")
    parser.add_argument("--batches", type=int, default=4, help="distinct batches (frames cached: batches x 8)")
    parser.add_argument("--objects", type=int, default=6, help="GT objects per image")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["scale=cpu", "fusion=smoe"])
    torch.manual_seed(0)
    model = instantiate(cfg.model)
    task = instantiate(cfg.task, model=model)
    for m in cfg.modalities:  # random experts: their cost, not their weights, is measured
        model.load_expert(m, instantiate(expert_config(cfg, m).model), freeze=cfg.experts.freeze)
    cache = feature_cache(cfg, model)
    assert isinstance(cache, FeatureCache), "the cpu-scale default job should cache its experts' features"
    optimizer = task.optimizer_factory(params=task.trainable())
    size, batch = (cfg.data.synth.height, cfg.data.synth.width), cfg.data.batch_size
    gen = torch.Generator().manual_seed(0)
    batches = [
        synthetic_batch([f"{k * batch + i:06d}" for i in range(batch)], size, args.objects, gen)
        for k in range(args.batches)
    ]
    task.train()

    def step(b: dict, variant: str) -> float:  # "none", "cold" (fills an empty cache) or "warm"
        task.feature_cache = {"none": None, "cold": FeatureCache(), "warm": cache}[variant]
        t0 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        loss = task.criterion(task(b), task.targets(b), size)["total"]
        loss.backward()
        optimizer.step()
        return 1000 * (time.perf_counter() - t0)

    step(batches[0], "none")  # warm-up
    task.feature_cache = cache
    for b in batches:  # fills the cache
        task(b)
    variants = ("none", "cold", "warm")
    times: dict[str, list[float]] = {v: [] for v in variants}
    for i in range(args.steps):
        for variant in variants[i % 3 :] + variants[: i % 3]:
            times[variant].append(step(batches[i % len(batches)], variant))
    before, cold, after = (statistics.median(times[v]) for v in variants)
    per_frame = cache.nbytes / len(cache.frames)
    frozen = sum(p.numel() for p in model.parameters() if not p.requires_grad)
    trained = sum(p.numel() for p in model.parameters() if p.requires_grad)
    print(
        f"stage 2, stage {cfg.stage.name}, fusion {cfg.fusion.name}, batch {batch}, input {size[0]}x{size[1]}, "
        f"ResNet-{cfg.model.backbone.depth} x{cfg.scale.width}, FPN {cfg.scale.fpn_channels}; "
        f"{frozen / 1e6:.2f} M frozen + {trained / 1e6:.2f} M trained params; {args.objects} GT/image; "
        f"{torch.get_num_threads()} threads"
    )
    print(f"  step, experts run (no cache)   {before:8.1f} ms   (median of {args.steps})")
    print(f"  step, features cached (warm)   {after:8.1f} ms   (median of {args.steps})   x{before / after:.2f}")
    print(f"  step that fills the cache      {cold:8.1f} ms   (median of {args.steps})")
    fit_frames = round(FIT_SHARE * cfg.data.synth.frames)
    print(
        f"  cache: {per_frame / 2**10:.0f} KiB per frame (float32, P3..P7 x 2 modalities); "
        f"{cache.nbytes / 2**20:.1f} MiB for these {len(cache.frames)} frames; "
        f"{per_frame * fit_frames / 2**20:.0f} MiB for the {fit_frames} train + val frames of the cpu scale's "
        f"{cfg.data.synth.frames}"
    )


if __name__ == "__main__":
    main()
