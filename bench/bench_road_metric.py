"""What the road measures' counting costs a BiFNet job (ablate.metrics.road): one evaluation batch of 8 frames on
the devkit's 800 x 400 BEV grid, counted as a test step counts it (each frame's level histograms, which the metric
adds) and as it was counted before (``torch.bucketize`` for the levels, the metric's own pass, then the frames'
histograms again). The counts of both ways are checked equal; milliseconds per batch and branch. 1 thread, as a job.

    PYTHONPATH=. python bench/bench_road_metric.py

Measured (AMD EPYC family 25 model 17, fp32, 1 thread): a step 68-78 ms now, before 163-173 (validation) and
305-333 (test); with 2 threads 54 ms against 85 and 163. A BiFNet Table IV fused row (``row=bifnet_dst_cbf``, 300
test frames, both branches, 3 epochs of 100 validation frames) took 6 s less to test (17 s against 23), its metrics
and its test frames' counts byte for byte the same.
"""

from __future__ import annotations

import time

import torch

from ablate.hardware import cpu
from ablate.metrics.road import NUM_THRESHOLDS, RoadMaxF, frame_histograms


def searched(preds: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The frames' level histograms with the levels found by ``torch.bucketize``, frame by frame."""
    thresholds = torch.arange(NUM_THRESHOLDS, dtype=preds.dtype) / (NUM_THRESHOLDS - 1)
    level, bins = torch.bucketize(preds, thresholds, right=True), NUM_THRESHOLDS + 1
    return torch.stack(
        [
            torch.cat([torch.bincount(lv[tg & va], minlength=bins), torch.bincount(lv[~tg & va], minlength=bins)])
            for lv, tg, va in zip(level, target, valid)
        ]
    )


def timed(step, repeats: int = 10) -> float:
    step()
    began = time.perf_counter()
    for _ in range(repeats):
        step()
    return (time.perf_counter() - began) / repeats * 1000


def main() -> None:
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    shape = (8, 800, 400)
    target = torch.rand(shape, generator=gen) < 0.3
    preds = (0.3 * target + 0.7 * torch.rand(shape, generator=gen)).clamp(0, 1)
    valid = torch.rand(shape, generator=gen) < 0.9
    assert torch.equal(frame_histograms(preds, target, valid), searched(preds, target, valid))

    def now() -> None:  # validation and test alike (ablate.tasks.road_bev.task.RoadTask._eval_step)
        metric = RoadMaxF()
        metric.update(histograms=metric.histograms(preds, target, valid))

    def before(test: bool) -> None:
        RoadMaxF().update(histograms=searched(preds, target, valid))  # the metric's own pass, as it was
        if test:  # the test frames' histograms, counted again
            searched(preds, target, valid)

    print(f"{cpu().model}, 1 thread; a batch of {shape[0]} frames on the {shape[1]} x {shape[2]} BEV grid, a branch")
    print(
        f"a step now: {timed(now):.0f} ms; before: validation {timed(lambda: before(False)):.0f} ms, "
        f"test {timed(lambda: before(True)):.0f} ms"
    )


if __name__ == "__main__":
    main()
