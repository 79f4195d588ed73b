"""The cost of AP over one resample of the test frames, re-accumulated from each frame's matched detections
(ablate.metrics.accumulate), against running the evaluator again.

    python bench/ap_resample.py [frames=300]

Makes KITTI-like frames (the devkit tests' generator) and instance masks, evaluates them once with KittiAP and
MaskAP, keeps their rows per frame, and prints per metric: the evaluator's own time, the frames' term a table
computes per row and seed (AP re-accumulated over ``ablate.tables.frames.AP_DRAWS`` draws of the frames with
replacement, ``ap_resampled``), and the delete-one jackknife over every frame it replaced for AP.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ablate import hardware  # noqa: E402
from ablate.metrics.accumulate import as_arrays, coco_ap, kitti_ap  # noqa: E402
from ablate.tables.frames import AP_DRAWS, ap_resampled, frame_draws  # noqa: E402
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
    frames = [f"{i:06d}" for i in range(n)]
    draws = frame_draws(n)

    def resampled(rows: dict, metric: str) -> float:
        long = pd.DataFrame(rows).assign(frame=lambda d: d["index"].map("{:06d}".format))
        return timed(lambda: ap_resampled(long, metric, frames, draws), 1)

    kitti = kitti_metric(random_frames(0, n_images=n))
    rows = as_arrays(kitti.frame_rows("Car", 1))
    whole = timed(lambda: kitti.compute(), 1)
    one = resampled(rows, "car_moderate")
    jack = timed(lambda: [kitti_ap(rows, "Car", 1, 11, np.delete(np.arange(n), i)) for i in range(n)], 1)
    print(
        f"KITTI box AP (Car, moderate): evaluator {whole:.3f} s (every class and level); {AP_DRAWS} draws {one:.2f} s; "
        f"jackknife over {n} frames {jack:.2f} s; {len(rows['kind'])} rows"
    )
    coco = mask_ap(random_instances(0, n_images=n))
    rows = as_arrays(coco.frame_rows("segm"))
    whole = timed(lambda: coco.compute(), 1)
    one = resampled(rows, "map")
    jack = timed(lambda: [coco_ap(rows, np.delete(np.arange(n), i)) for i in range(n)], 1)
    print(
        f"COCO mask AP: evaluator {whole:.3f} s (masks and boxes); {AP_DRAWS} draws {one:.2f} s; "
        f"jackknife over {n} frames {jack:.2f} s; {len(rows['kind'])} rows"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
