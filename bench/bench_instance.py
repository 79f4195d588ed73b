"""Time the YOLACT-style head: forward, SMoE eq. 7 loss (+ backward) and decode, at batch 8 on FPN features
of a 128x416 input with C=64 channels. Prints milliseconds per batch (median of the repeats).

    PYTHONPATH=. python bench/bench_instance.py [--repeats 5] [--objects 6] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from ablate.metrics.coco import MaskAP
from ablate.tasks.instance import YolactHead, YolactLoss, decode

IMAGE, CHANNELS, BATCH = (128, 416), 64, 8
LEVELS = [(16, 52), (8, 26), (4, 13), (2, 7), (1, 4)]  # P3..P7, strides 8..128


def synthetic_targets(n_objects: int, gen: torch.Generator) -> list[dict]:
    targets = []
    for _ in range(BATCH):
        h = torch.randint(10, 60, (n_objects,), generator=gen)
        w = (h * (1 + torch.rand(n_objects, generator=gen))).long()
        y1 = (torch.rand(n_objects, generator=gen) * (IMAGE[0] - h)).long()
        x1 = (torch.rand(n_objects, generator=gen) * (IMAGE[1] - w)).long()
        boxes = torch.stack([x1, y1, x1 + w, y1 + h], 1).float()
        masks = torch.zeros(n_objects, *IMAGE, dtype=torch.bool)
        for i, (a, b, c, d) in enumerate(boxes.long().tolist()):
            masks[i, b:d, a:c] = True
        targets.append({"boxes": boxes, "labels": torch.randint(0, 2, (n_objects,), generator=gen), "masks": masks})
    return targets


def timed(fn, repeats: int) -> tuple[float, object]:
    out, times = None, []
    for _ in range(repeats + 1):  # first call warms up
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times[1:]), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--objects", type=int, default=6, help="GT objects per image")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    head, loss_fn = YolactHead(in_channels=CHANNELS), YolactLoss()
    feats = [torch.randn(BATCH, CHANNELS, h, w, generator=gen) for h, w in LEVELS]
    targets = synthetic_targets(args.objects, gen)

    ms_fwd, outputs = timed(lambda: head(feats), args.repeats)
    ms_loss, _ = timed(lambda: loss_fn(outputs, targets, IMAGE), args.repeats)

    def train_step() -> None:
        head.zero_grad()
        loss_fn(head(feats), targets, IMAGE)["total"].backward()

    ms_step, _ = timed(train_step, args.repeats)
    with torch.no_grad():
        outputs = head(feats)
    ms_dec, dets = timed(lambda: decode(outputs, IMAGE, score_thresh=0.05, nms_iou=0.5, top_k=200), args.repeats)
    metric = MaskAP()
    ms_ap, _ = timed(lambda: (metric.reset(), metric.update(dets, targets), metric.compute()), args.repeats)

    n_params = sum(p.numel() for p in head.parameters())
    n_anchors = sum(h * w for h, w in LEVELS) * head.anchors.num_per_location
    print(
        f"YOLACT head, batch {BATCH}, input {IMAGE[0]}x{IMAGE[1]}, C={CHANNELS}, k={head.num_prototypes}, "
        f"{n_anchors} anchors, {n_params / 1e6:.2f} M params, {args.objects} GT/image, "
        f"{torch.get_num_threads()} threads"
    )
    print(f"  head forward                 {ms_fwd:8.1f} ms")
    print(f"  loss forward                 {ms_loss:8.1f} ms")
    print(f"  forward + loss + backward    {ms_step:8.1f} ms")
    print(f"  decode (Fast NMS + masks)    {ms_dec:8.1f} ms   ({sum(len(d['scores']) for d in dets)} detections)")
    print(f"  MaskAP update + compute      {ms_ap:8.1f} ms")


if __name__ == "__main__":
    main()
