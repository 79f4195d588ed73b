"""The paper check's estimates for a GPU (:mod:`ablate.capacity.check`), from a row's measurement
(:mod:`ablate.capacity.measure`) and its recipe (:func:`ablate.capacity.rows.recipe`); no GPU ran them.

- GPU memory (:func:`gpu_memory`) at the recipe's batch (``data.batch_size`` of ``conf/recipe/<task>_paper.yaml`` or
  of the scale) under ``trainer=gpu``'s bf16-mixed: fp32 weights + fp32 gradients + the optimiser state as measured
  + the batch-1 activations x batch x :data:`BF16_ACTIVATIONS` (autocast keeps convolution and matmul outputs in
  bf16, half of fp32; an assumption, not a measurement) + :data:`CUDA_OVERHEAD` (context and cuDNN workspace).
- GPU-hours of a row (:func:`gpu_hours`, :func:`row_hours`): (3 x its trainable MACs + 1 x its frozen MACs) x 2 FLOPs
  a frame x the frames the recipe trains on (optimiser steps x batch) x the scale's seeds, over the GPU's dense bf16
  peak x :data:`UTILISATION`. The reading: the trainable parts run forward and backward (backward ~ twice the
  forward); the frozen experts of a two-stage row (SMoE §4.3, stage 2 "with fixed weights of each expert network")
  run forward only, no gradient reaching them, every step unless their feature cache fits the GPU
  (:func:`cache_share`, as :class:`ablate.jobs.experts.FeatureCache` decides on a GPU), when they run once per
  training and validation frame. Fine-tuned experts (``experts.freeze: false``, BiFNet's paper recipe) are trainable
  parts. A table also pays for the experts its fused rows start from (stage 1: 3 x each expert's MACs, its own
  steps, every seed), counted once per table (:func:`table_hours`); validation passes are not counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ablate.jobs.experts import GPU_CACHE_SHARE


@dataclass(frozen=True)
class Gpu:
    """A GPU the estimates are for: its name, dense (no sparsity) bf16 tensor-core peak and memory, and the source."""

    name: str
    bf16_tflops: float
    memory_gib: float
    source: str


#: NVIDIA H100 SXM5 80 GB: 989.4 dense bf16 TFLOPs (the datasheet's 1,979 is with 2:4 sparsity; NVIDIA H100 Tensor
#: Core GPU datasheet, and the Hopper architecture whitepaper's table 3).
H100 = Gpu("H100 SXM 80 GB", 989.4, 80.0, "NVIDIA H100 datasheet: 1,979 TFLOPs bf16 with sparsity, half dense")
#: NVIDIA A100 SXM4 80 GB: 312 dense bf16 TFLOPs (NVIDIA A100 Tensor Core GPU datasheet).
A100 = Gpu("A100 SXM 80 GB", 312.0, 80.0, "NVIDIA A100 datasheet: 312 TFLOPs bf16 dense")
#: The GPU of the estimates, and the others given per table.
GPU, OTHER_GPUS = H100, (A100,)
#: The share of the peak a convolutional network's training sustains (a working assumption: dense convnets at
#: these sizes reach 30-50 % model FLOPs utilisation in bf16).
UTILISATION = 0.40
#: Bytes of a saved activation under bf16 autocast over its fp32 bytes.
BF16_ACTIVATIONS = 0.5
#: The CUDA context, cuDNN / cuBLAS workspaces and the allocator's slack, in bytes.
CUDA_OVERHEAD = 1.5 * 2**30


def gpu_memory(m: dict[str, Any], batch: int) -> float:
    """Estimated GPU memory in bytes of a training step at ``batch`` under bf16-mixed (module docstring)."""
    return (
        m["weights"] + m["grads"] + m["optimizer_state"] + m["activations"] * batch * BF16_ACTIVATIONS + CUDA_OVERHEAD
    )


def gpu_hours(
    macs: int,
    frames: int,
    seeds: int = 1,
    gpu: Gpu = GPU,
    frozen: int = 0,
    frozen_frames: float | None = None,
) -> float:
    """GPU-hours of training on ``frames`` frames (each seed) of a network of ``macs`` MACs a frame, ``frozen`` of
    them in frozen parts (the experts of a two-stage row, :class:`FrozenMacs`): 3 x the trainable MACs a frame
    (forward, and backward at about twice the forward) + 1 x the frozen MACs (forward only: no gradient reaches
    them) on ``frozen_frames`` frames (default ``frames``: the experts run every step; fewer where a feature cache
    holds their features, :func:`frozen_frames`), x 2 FLOPs a MAC, over ``gpu``'s dense bf16 peak x
    :data:`UTILISATION`."""
    runs = frames if frozen_frames is None else frozen_frames
    flops = 2 * (3 * (macs - frozen) * frames + frozen * runs) * seeds
    return flops / (gpu.bf16_tflops * 1e12 * UTILISATION) / 3600


def cache_share(m: dict[str, Any], entry: dict[str, Any], gpu: Gpu = GPU) -> float:
    """The share of the training and validation frames whose frozen features a job's feature cache holds on
    ``gpu`` (:class:`ablate.jobs.experts.FeatureCache`): 0 without one (``feature_bytes`` 0: none was built, as for
    fine-tuned experts or augmented data) or where it turns itself off, its features of ``fit_frames`` frames being
    over ``GPU_CACHE_SHARE`` of the memory free at the first batch (taken as the GPU's less the weights and
    :data:`CUDA_OVERHEAD`); else what its cap (``experts.cache_max_gb``) holds of them."""
    size = m.get("feature_bytes") or 0
    if not size:
        return 0.0
    need = size * entry["fit_frames"]
    if need > GPU_CACHE_SHARE * (gpu.memory_gib * 2**30 - m["weights"] - CUDA_OVERHEAD):
        return 0.0
    cap = entry.get("cache_max_bytes")
    return 1.0 if cap is None else min(1.0, cap / need)


def frozen_frames(m: dict[str, Any], entry: dict[str, Any], gpu: Gpu = GPU) -> float:
    """The frames the frozen experts of a row run on, each seed: once for each frame its feature cache holds (the
    first epoch's, and the validation frames'), every step for the others (:func:`cache_share`)."""
    share = cache_share(m, entry, gpu)
    return share * entry["fit_frames"] + (1 - share) * entry["steps"] * entry["batch"]


def split(entry: dict[str, Any], measured: dict[str, Any]) -> tuple[dict[str, Any], int] | None:
    """A row's measurement and its frozen MACs (0 for a row without frozen experts); None where it is not measured
    or failed, or where a row on frozen experts has no count of its frozen MACs."""
    m = measured.get(entry["key"])
    if m is None or "error" in m:
        return None
    if not entry.get("frozen"):
        return m, 0
    return (m, int(m["macs_frozen"])) if m.get("macs_frozen") is not None else None


def row_hours(entry: dict, measured: dict, gpu: Gpu = GPU) -> float | None:
    """GPU-hours of a row's own training, all seeds (None when not measured): :func:`gpu_hours` of its trainable
    and frozen MACs, its frozen experts running on :func:`frozen_frames`."""
    got = split(entry, measured)
    if got is None:
        return None
    m, frozen = got
    runs = frozen_frames(m, entry, gpu) if frozen else None
    return gpu_hours(m["macs"], entry["steps"] * entry["batch"], entry["seeds"], gpu, frozen, runs)


def table_hours(entries: list[dict], measured: dict, gpu: Gpu = GPU) -> tuple[float, list[str]]:
    """GPU-hours of a table: its rows' trainings and the experts its fused rows start from (stage 1: each expert,
    told apart by what it trains and for how many steps, once per table and seed; an expert that is a row of the
    table, a single-modal row, is that row), all seeds; and the rows or experts not measured. Tables that share
    experts (smoe_table1 and smoe_table2) each count them."""
    total, missing, experts = 0.0, [], {}
    own = {(e["key"], e["steps"], e["batch"]) for e in entries}
    for e in entries:
        hours = row_hours(e, measured, gpu)
        if hours is None:
            missing.append(e["row"])
        else:
            total += hours
        for modality, key in e["experts"].items():
            expert = (key, e["expert_steps"], e["batch"])
            if expert not in own and expert not in experts:
                experts[expert] = (modality, e)
    for (key, steps, batch), (modality, e) in experts.items():
        m = measured.get(key)
        if m is None or "error" in m:
            missing.append(f"the {modality} expert")
        else:
            total += gpu_hours(m["macs"], steps * batch, e["seeds"], gpu)
    return total, missing
