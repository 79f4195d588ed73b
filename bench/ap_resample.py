"""The cost of AP over one resample of the test frames, re-accumulated from each frame's matched detections
(ablate.metrics.accumulate), against running the evaluator again.

    python bench/ap_resample.py [frames=300]

Makes KITTI-like frames (the devkit tests' generator) and instance masks, evaluates them once with KittiAP and
MaskAP, keeps their rows per frame, and prints per metric: the evaluator's own time, one re-accumulation over a
resample of the frames, and the delete-one jackknife over every frame (what a table computes per row and seed).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ablate import hardware  # noqa: E402
from ablate.metrics.accumulate import as_arrays, coco_ap, kitti_ap  # noqa: E402
from tests.metrics.test_accumulate import kitti_metric, mask_ap, random_instances  # noqa: E402
from tests.metrics.test_kitti import random_frames  # noqa: E402


def timed(f, repeat: int = 5) -> float:  # type: ignore[no-untyped-def]
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - start)
    return float(best)


def main(argv: list[str]) -> int:
    n = int(dict(a.split("=", 1) for a in argv if "=" in a).get("frames", 300))
    machine = hardware.cpu()
    print(f"CPU: {machine.model} ({machine.isa}); {n} frames, best of 5")
    rng = np.random.default_rng(0)
    draw = np.sort(rng.integers(0, n, n))  # one bootstrap resample of the frames (indices, with repeats)
    kitti = kitti_metric(random_frames(0, n_images=n))
    rows = as_arrays(kitti.frame_rows("Car", 1))
    whole = timed(lambda: kitti.compute(), 1)
    one = timed(lambda: kitti_ap(rows, "Car", 1, 11, np.unique(draw)))
    jack = timed(lambda: [kitti_ap(rows, "Car", 1, 11, np.delete(np.arange(n), i)) for i in range(n)], 1)
    print(
        f"KITTI box AP (Car, moderate): evaluator {whole:.3f} s (every class and level); one resample {1e3 * one:.2f} ms; "
        f"jackknife over {n} frames {jack:.2f} s; {len(rows['kind'])} rows"
    )
    coco = mask_ap(random_instances(0, n_images=n))
    rows = as_arrays(coco.frame_rows("segm"))
    whole = timed(lambda: coco.compute(), 1)
    one = timed(lambda: coco_ap(rows, np.unique(draw)))
    jack = timed(lambda: [coco_ap(rows, np.delete(np.arange(n), i)) for i in range(n)], 1)
    print(
        f"COCO mask AP: evaluator {whole:.3f} s (masks and boxes); one resample {1e3 * one:.2f} ms; "
        f"jackknife over {n} frames {jack:.2f} s; {len(rows['kind'])} rows"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
