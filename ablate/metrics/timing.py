"""Compute time of a model, as ChiNet Tables II-V report it ("Comp Time (ms)")."""
from __future__ import annotations

import statistics
import time

import torch
from torch import nn


def forward_time_ms(model: nn.Module, batch: dict, warmup: int = 3, repeats: int = 10) -> float:
    """Median wall time in ms of one forward pass at batch size 1, after ``warmup`` untimed passes.

    The first sample of ``batch`` is used; tensors move to the model's device. The thread count and device are
    recorded by the caller, since the figure means nothing without them.
    """
    device = next(model.parameters()).device
    sample = {k: v[:1].to(device) for k, v in batch.items() if torch.is_tensor(v)}
    was_training = model.training
    model.eval()
    times = []
    with torch.inference_mode():
        for i in range(warmup + repeats):
            if device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            model(sample)
            if device.type == "cuda":
                torch.cuda.synchronize()
            if i >= warmup:
                times.append(time.perf_counter() - start)
    model.train(was_training)
    return 1000.0 * statistics.median(times)
