"""The paper path on a GPU: training steps of a row at ``scale=paper`` with ``trainer=gpu``'s numerics (bf16 autocast,
fp32 weights), at the recipe's batch, against the estimates of ``results/paper_scale.md``.

    PYTHONPATH=. python bench/bench_paper_gpu.py [--rows smoe_table2:smoe_fpn,chinet_table2:chinet]
        [--steps 20] [--warmup 5] [--precision bf16,fp32] [--set "task.optimizer.lr=1e-4"] [--deterministic]
        [--device cuda] [--json results/paper_scale_gpu.json]

Each row is built as the paper check builds it (:func:`ablate.capacity.measure._build`: generated frames at the
paper's 375 x 1242, the row's model, task, frozen experts and training corruptions), with a training batch of the
recipe's ``data.batch_size`` distinct frames (``distinct_frames`` in the JSON; runs before it counted them used one
frame repeated) and no feature cache (at the paper's sizes the experts run every step: ``results/paper_scale.md``'s
feature-cache note). The experts of a fused row are freshly built, not trained: its losses say nothing of stage 2's
training, only its step time and memory do. Then ``--warmup`` steps untimed and ``--steps`` timed on that one batch,
each: forward and loss under ``torch.autocast(bf16)`` (``--precision fp32``: without), backward, the recipe's
optimiser and scheduler step, the device synchronised. One test step follows (the task's test conditions, its
metrics computed). A loss :data:`DIVERGED` times the first step's, or non-finite, stops the row as diverged, with
:func:`diagnose`'s account of where the values blow up.

Printed per row: the GPU, the median training step, the step the estimate assumes (:func:`ablate.capacity.estimates.
gpu_hours` for one step of the batch: (3 x trainable + frozen MACs) x 2 FLOPs a frame at 40 % of the dense bf16 peak
of an H100 SXM, which an H200 shares), the achieved share of that peak, the peak memory allocated and reserved after
the warm-up against :func:`~ablate.capacity.estimates.gpu_memory`'s estimate, the loss at the first and the last
step, and the test step. A row that fails or diverges prints why and the others go on; the exit status is then 1.

The estimates use the row's CPU measurement in ``results/paper_scale.json`` (``python -m ablate.check_paper``); a
row not measured there prints measured figures alone. ``--json`` merges the figures into a file that
``python -m ablate.check_paper`` lists in ``results/paper_scale.md``. Without a CUDA device (``--device cpu``) the
same steps run in fp32 on the CPU, to try the script at small sizes (``--scale smoke``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import statistics
import sys
import tempfile
import time
import traceback
import warnings
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from ablate.capacity.estimates import GPU, gpu_hours, gpu_memory
from ablate.capacity.measure import _build, _loss, sample_config
from ablate.capacity.rows import measure_key, measured_config, recipe

ROWS = "smoe_table2:smoe_fpn,smoe_table1:smoe_rgb,dgfn_table1:dgfn,chinet_table2:chinet,bifnet_table4:bifnet_dst_cbf"
GIB = 2**30
#: A training loss this many times the first step's (or non-finite) stops the row: diverged.
DIVERGED = 1e3


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _stored(cfg: Any) -> dict[str, Any] | None:
    """The row's CPU measurement in results/paper_scale.json, if any."""
    store = Path("results/paper_scale.json")
    if not store.is_file():
        return None
    return json.loads(store.read_text())["measured"].get(measure_key(cfg))


def _nonfinite(tree: Any, prefix: str = "") -> list[str]:
    """The names of the non-finite tensors in a model's outputs (dicts and lists walked)."""
    if torch.is_tensor(tree):
        return [] if not tree.is_floating_point() or bool(torch.isfinite(tree).all()) else [prefix or "output"]
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, (list, tuple)) else []
    return [name for k, v in items for name in _nonfinite(v, f"{prefix}.{k}" if prefix else str(k))]


def _largest(tree: Any) -> float:
    """The largest magnitude among the tensors of ``tree`` (nan where one is NaN)."""
    if torch.is_tensor(tree):
        if not tree.is_floating_point() or tree.numel() == 0:
            return 0.0
        return float("nan") if bool(torch.isnan(tree).any()) else float(tree.detach().abs().max())
    items = tree.values() if isinstance(tree, dict) else tree if isinstance(tree, (list, tuple)) else []
    values = [_largest(v) for v in items]
    return float("nan") if any(math.isnan(v) for v in values) else max(values, default=0.0)


def diagnose(task: Any, batch: dict, autocast: Any, limit: float = 1e4) -> str:
    """Where a non-finite first loss comes from: the first module (in the order they run) whose output is NaN,
    infinite or larger than ``limit`` in magnitude, with its input's magnitude; the model's non-finite outputs; and,
    for a task with a criterion (the instance task), the loss terms."""
    seen: list[str] = []

    def hook(name: str) -> Any:
        def check(module: Any, inputs: Any, output: Any) -> None:
            top = _largest(output)
            if not seen and not (top <= limit):  # nan compares False
                seen.append(
                    f"first large output: {name} ({type(module).__name__}) {top:.3g} from input {_largest(inputs):.3g}"
                )

        return check

    handles = [m.register_forward_hook(hook(n)) for n, m in task.named_modules() if n]
    try:
        with torch.no_grad(), autocast:
            outputs = task(batch)
            said = seen + [f"non-finite outputs: {_nonfinite(outputs) or 'none'}"]
            if hasattr(task, "criterion") and hasattr(task, "targets"):
                losses = task.criterion(outputs, task.targets(batch), task.image_size(batch))
                said.append("loss terms: " + ", ".join(f"{k} {float(v):.4g}" for k, v in losses.items()))
    finally:
        for h in handles:
            h.remove()
    return "; ".join(said)


def bench_row(
    spec: str,
    device: torch.device,
    steps: int,
    warmup: int,
    scale: str,
    precision: str = "bf16",
    overrides: list[str] | None = None,
) -> dict[str, Any]:
    """Training and test steps of ``spec`` (``experiment:row``) on ``device``: the module docstring's figures."""
    experiment, row = spec.split(":")
    base = [] if scale == "paper" else [f"scale={scale}"]
    overrides = base + list(overrides or [])
    cfg = measured_config(experiment, row, overrides=overrides)
    plan = recipe(cfg)
    batch_size = plan["batch"]
    with tempfile.TemporaryDirectory() as data_dir:
        small = sample_config(cfg, data_dir, frames=math.ceil(batch_size / 0.6) + 2)  # the 60 % split holds a batch
        start = time.perf_counter()
        built = _build(cfg, small, batch_size=batch_size)
        build_s = time.perf_counter() - start
    task, model = built["task"], built["model"]
    task.feature_cache = None
    task.to(device)
    batch = move_data_to_device(built["batch"], device)
    test_batch = move_data_to_device(built["test_batch"], device)
    trainable = task.trainable()
    optimizer, scheduler = task.optimizers_for(trainable, plan["steps"])
    bf16 = precision == "bf16" and device.type == "cuda"
    autocast = torch.autocast(device.type, dtype=torch.bfloat16) if bf16 else nullcontext()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times, losses, diverged = [], [], None
    task.train()
    for i in range(warmup + steps):
        if i == warmup and device.type == "cuda":  # the steady state's peak: not cuDNN's autotuning at the start
            torch.cuda.reset_peak_memory_stats(device)
        _sync(device)
        start = time.perf_counter()
        try:
            with autocast:
                loss = _loss(task.training_step(batch, i))
        except FloatingPointError as exc:  # the task's NonFiniteLossError
            diverged = f"step {i}: {exc} ({diagnose(task, batch, autocast)})"
            break
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        _sync(device)
        if i >= warmup:
            times.append(time.perf_counter() - start)
        losses.append(float(loss.detach()))
        if losses[-1] > DIVERGED * max(abs(losses[0]), 1.0):
            diverged = f"step {i}: loss {losses[-1]:.4g} from {losses[0]:.4g} ({diagnose(task, batch, autocast)})"
            break
    out: dict[str, Any] = {
        "row": spec,
        "precision": precision if device.type == "cuda" else "fp32",
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "batch": batch_size,
        "distinct_frames": built["distinct_frames"],
        "build_s": build_s,
        "step_s": statistics.median(times) if times else None,
        "loss_first": losses[0],
        "loss_last": losses[-1] if losses else None,
        "losses": losses,
        "overrides": overrides,
    }
    if diverged:
        out["diverged"] = diverged
    if device.type == "cuda" and times:
        out["peak_allocated_gib"] = torch.cuda.max_memory_allocated(device) / GIB
        out["peak_reserved_gib"] = torch.cuda.max_memory_reserved(device) / GIB
    task.eval()
    _sync(device)
    start = time.perf_counter()
    with torch.no_grad(), autocast:
        task.on_test_epoch_start()
        task.test_step(test_batch, 0)
        task.on_test_epoch_end()
    _sync(device)
    out["test_s"] = time.perf_counter() - start
    stored = _stored(cfg)
    if stored is None and overrides != base:  # --set changed the config: the estimate of the row as configured
        stored = _stored(measured_config(experiment, row, overrides=base))
        out["estimate_of"] = "the row without --set"
    if stored is not None:
        est = gpu_hours(stored["macs"], batch_size, frozen=stored.get("macs_frozen", 0)) * 3600
        out["estimated_step_s"] = est
        out["mfu"] = est * 0.40 / out["step_s"]  # the share of the dense bf16 peak achieved
        out["estimated_mem_gib"] = gpu_memory(stored, batch_size) / GIB
    del task, model, optimizer, batch
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return out


def _line(r: dict[str, Any]) -> str:
    def f(key: str, fmt: str) -> str:
        return format(r[key], fmt) if key in r else "-"

    return (
        f"| {r['row']} | {r['precision']} | {r['batch']} | {f('step_s', '.3f')} | {f('estimated_step_s', '.3f')} | {f('mfu', '.1%')} | "
        f"{f('peak_allocated_gib', '.1f')} / {f('peak_reserved_gib', '.1f')} | {f('estimated_mem_gib', '.1f')} | "
        f"{f('loss_first', '.3f')} -> {f('loss_last', '.3f')} | {f('test_s', '.2f')} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", default=ROWS)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--scale", default="paper")
    parser.add_argument("--precision", default="bf16", help="bf16 (trainer=gpu's autocast), fp32, or both: bf16,fp32")
    parser.add_argument("--json", default=None)
    parser.add_argument("--set", default="", help="hydra overrides for every row, space-separated")
    parser.add_argument("--deterministic", action="store_true", help="cuDNN without autotuning, deterministic kernels")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    warnings.filterwarnings("ignore")
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = device.type == "cuda" and not args.deterministic
    if args.deterministic:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"device: {name}, torch {torch.__version__}; estimates for {GPU.name} at 40 % of {GPU.bf16_tflops} TFLOPs")
    print(
        "| row | precision | batch | step (s) | estimated step (s) | of the bf16 peak | peak alloc. / reserved (GiB) "
        "| estimated mem. (GiB) | loss first -> last | test step (s) |"
    )
    print("|:--|:--|--:|--:|--:|--:|--:|--:|:--|--:|")
    results, failed = [], 0
    for spec, precision in [(s, p) for s in args.rows.split(",") for p in args.precision.split(",")]:
        try:
            r = bench_row(spec, device, args.steps, args.warmup, args.scale, precision, args.set.split())
        except Exception as exc:  # a row's failure is its line; the others go on
            failed += 1
            print(f"| {spec} | {precision} | failed: {type(exc).__name__}: {exc} |", flush=True)
            traceback.print_exc(file=sys.stdout)
            results.append({"row": spec, "precision": precision, "error": f"{type(exc).__name__}: {exc}"})
            continue
        results.append(r)
        print(_line(r), flush=True)
        if "diverged" in r:
            failed += 1
            print(f"  diverged at {r['diverged']}; losses {[round(v, 3) for v in r['losses']]}", flush=True)
    if args.json:
        for r in results:
            r.update(deterministic=args.deterministic, torch=torch.__version__, date=time.strftime("%Y-%m-%d"))
        merge(Path(args.json), results)
    return 1 if failed else 0


def _key(r: dict[str, Any]) -> tuple:
    return r["row"], r.get("precision"), tuple(r.get("overrides") or ()), bool(r.get("deterministic"))


def merge(path: Path, results: list[dict[str, Any]]) -> None:
    """Write ``results`` into the JSON list at ``path``: an entry of the same row, precision, overrides and
    determinism is replaced, the others kept (several runs fill one file, e.g. results/paper_scale_gpu.json, which
    ``python -m ablate.check_paper`` lists in results/paper_scale.md)."""
    old = json.loads(path.read_text()) if path.is_file() else []
    new = {_key(r) for r in results}
    path.write_text(json.dumps([r for r in old if _key(r) not in new] + results, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
