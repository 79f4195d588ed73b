"""The paper path, exercised on the CPU: every row of every table at ``scale=paper`` builds its data, model and task and
runs one training step and one evaluation step at batch 1, with its memory and GPU time estimated from them.

``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=40]`` (:mod:`ablate.check_paper`). Per row:

- the job's config (:func:`ablate.config.compose` of ``experiment=<table> row=<row> scale=paper``) on two frames of
  the generated dataset at the paper's resolution (``data.synth`` height and width of ``conf/scale/paper.yaml``:
  KITTI's 375 x 1242), generated once in a temporary folder; batch 1, no loader workers; the data module as
  configured otherwise (BiFNet's paper augmentation included);
- the model and task built with hydra's ``instantiate`` as :mod:`ablate.run.job` does, with the frozen experts of a
  two-stage row (SMoE §4.3; BiFNet §V-B) loaded into the fused model from freshly built experts
  (:meth:`load_expert` with ``experts.freeze``), so that what is frozen is what a job freezes;
- one training step (the row's training corruptions, forward, loss, backward, the recipe's optimiser and scheduler
  step), then one test step with the task's test conditions, its metrics computed, on the CPU in fp32.

Figures (:func:`measure`): parameters; MACs of the training step's forward pass (``FlopCounterMode``: convolutions
and matrix products, MACs = FLOPs / 2, as :func:`ablate.run.latency.macs` counts them); the training and test steps'
wall times on this CPU; the peak RSS of the process that ran the row (each row runs in a fresh process,
``resource.getrusage``); the bytes of the tensors saved for backward at batch 1 (a ``saved_tensors_hooks`` pack hook,
each storage counted once, the parameters left out): the activation memory; the weights, gradients and optimiser
state after the step; the trainable parameters that got no gradient (``unused``: DDP needs
``find_unused_parameters`` for them, conf/trainer/ddp_*.yaml).

Estimates (:func:`gpu_memory`, :func:`gpu_hours`), for a GPU of :data:`GPU`:

- GPU memory at the recipe's batch (``data.batch_size`` of ``conf/recipe/<task>_paper.yaml`` or of the scale) under
  ``trainer=gpu``'s bf16-mixed: fp32 weights + fp32 gradients + the optimiser state as measured + the batch-1
  activations x batch x :data:`BF16_ACTIVATIONS` (autocast keeps convolution and matmul outputs in bf16, half of
  fp32; an assumption, not a measurement) + :data:`CUDA_OVERHEAD` (context and cuDNN workspace);
- GPU-hours: MACs x 2 FLOPs x 3 (forward + backward, backward ~ twice the forward) x the frames the recipe trains
  on (``max_steps`` x batch, else epochs x training frames), over the GPU's dense bf16 peak x :data:`UTILISATION`;
  per row for all of the scale's seeds, with the experts a two-stage row trains first (stage 1) counted once per
  table; validation passes are not counted.

The measurements are kept per measured configuration in ``results/paper_scale.json`` (rows of several tables with
one model, task and data share one); ``results/paper_scale.md`` lists every row of every table from them, a row
not measured here saying why.
"""

from __future__ import annotations

import concurrent.futures
import inspect
import json
import logging
import math
import multiprocessing
import platform
import resource
import subprocess
import tempfile
import time
import traceback
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict
from torch.utils.flop_counter import FlopCounterMode

from ablate import hardware
from ablate.config import CONF, compose
from ablate.data.datamodule import collate
from ablate.run.experts import expert_config, needed

log = logging.getLogger(__name__)


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
#: Frames of generated data each row reads (one training, one test frame after the 60/20/20 split).
FRAMES = 2
RESULTS = Path("results")


def experiments() -> list[str]:
    """The tables: ``conf/experiment/*.yaml``."""
    return sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def table_rows(experiment: str) -> list[str]:
    """The rows a table runs (its ``table.rows`` but those it only quotes, ``paper_only``)."""
    cfg = compose([f"experiment={experiment}", "scale=paper"])
    return [str(r["row"]) for r in cfg.table.rows if not r.get("paper_only")]


def job_config(experiment: str, row: str, overrides: Iterable[str] = ()) -> DictConfig:
    """The job config of ``row`` of table ``experiment`` at ``scale=paper``."""
    return compose([f"experiment={experiment}", f"row={row}", "scale=paper", *overrides])


def sample_config(cfg: DictConfig, data_dir: str, size: tuple[int, int] | None = None) -> DictConfig:
    """``cfg`` resolved, on :data:`FRAMES` generated frames under ``data_dir`` at the config's own resolution (or
    ``size``, height x width), batch 1, no loader workers; the data module's other options (augmentation, BEV grid,
    conditions) as configured."""
    small = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    with open_dict(small):
        synth = dict(small.data.get("synth") or {})
        height, width = size or (int(synth.get("height", 375)), int(synth.get("width", 1242)))
        small.data.root = None
        small.data.synth = {**synth, "frames": FRAMES, "seed": 0, "height": height, "width": width}
        small.data.data_dir = data_dir
        small.data.batch_size = 1
        small.data.num_workers = 0
        small.data.limit_frames = None
    return small


def measure_key(cfg: DictConfig) -> str:
    """What a measurement depends on: the resolved model, task, modalities, targets, data module (but the frames'
    count and the batch) and the experts' freezing; rows of several tables with the same share a measurement."""
    data = OmegaConf.to_container(cfg, resolve=True)
    datamodule = {k: v for k, v in data["data"].items() if k not in ("batch_size", "num_workers", "data_dir")}
    datamodule["synth"] = {k: v for k, v in (datamodule.get("synth") or {}).items() if k != "frames"}
    experts = data.get("experts") or {}
    key = {
        "model": data["model"],
        "task": data["task"],
        "data": datamodule,
        "freeze": experts.get("freeze") if needed_experts(cfg) else None,
    }
    return json.dumps(key, sort_keys=True, default=str)


def needed_experts(cfg: DictConfig) -> list[str]:
    """The modalities whose trained experts a row's fused model starts from (none for a row without two-stage
    training, an early fusion, or a single-modal row, which is itself an expert)."""
    return needed(cfg) if cfg.get("experts") and cfg.stage.name != "single" else []


class SavedTensors:
    """Bytes of the tensors autograd saves for backward while active (each storage once, parameters left out): the
    activation memory of a training step."""

    def __init__(self, params: Iterable[torch.Tensor]) -> None:
        self.skip = {p.untyped_storage().data_ptr() for p in params}
        self.seen: set[int] = set()
        self.nbytes = 0
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t)

    def _pack(self, t: torch.Tensor) -> torch.Tensor:
        if t.device.type != "meta":
            storage = t.untyped_storage()
            ptr = storage.data_ptr()
            if ptr not in self.skip and ptr not in self.seen:
                self.seen.add(ptr)
                self.nbytes += storage.nbytes()
        return t

    def __enter__(self) -> SavedTensors:
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._hooks.__exit__(*exc)


def _nbytes(tensors: Iterable[torch.Tensor]) -> int:
    return sum(t.numel() * t.element_size() for t in tensors)


def _loss(out: Any) -> torch.Tensor:
    return out["loss"] if isinstance(out, dict) else out


def recipe(cfg: DictConfig, train_frames: int | None = None) -> dict[str, Any]:
    """The row's training at the paper's sizes: batch, optimiser steps, frames trained on and seeds, for its own
    training and (two-stage rows) each expert's. ``train_frames``: the training split (60 % of ``data.synth``'s
    frames, as the generated dataset's split; 4489 on KITTI's 7481)."""
    synth = cfg.data.get("synth") or {}
    frames = train_frames or int(round(0.6 * int(synth.get("frames", 7481))))
    batch = int(cfg.data.batch_size)

    def steps(max_steps: Any, epochs: Any) -> int:
        if max_steps is not None and int(max_steps) > 0:
            return int(max_steps)
        return int(epochs) * math.ceil(frames / batch)

    trainer = cfg.trainer
    own = steps(trainer.get("max_steps"), trainer.get("max_epochs"))
    expert_epochs = (cfg.get("experts") or {}).get("max_epochs")
    expert_steps = steps(trainer.get("max_steps"), expert_epochs if expert_epochs is not None else trainer.max_epochs)
    single = cfg.get("experts") and cfg.stage.name == "single"
    return {
        "batch": batch,
        "train_frames": frames,
        "steps": expert_steps if single else own,
        "expert_steps": expert_steps,
        "seeds": int(cfg.scale.seeds),
        "optimizer": str(cfg.task.optimizer._target_).rsplit(".", 1)[-1],
    }


def measure(cfg: DictConfig, small: DictConfig, steps: int = 1000) -> dict[str, Any]:
    """One training and one test step of job config ``cfg`` on the frames of ``small`` (:func:`sample_config`), in
    this process: the figures of the module's docstring (times in s, memory in bytes). ``steps``: the schedule's
    length the scheduler is built for."""
    L.seed_everything(int(small.seed), workers=True, verbose=False)
    datamodule = instantiate(small.data)
    datamodule.setup("fit")
    train = datamodule.datasets["train"]
    test = datamodule.datasets["test"] if len(datamodule.datasets["test"]) else train
    start = time.perf_counter()
    batch, test_batch = collate([train[0]]), collate([test[0]])
    data_s = time.perf_counter() - start
    model = instantiate(small.model)
    task = instantiate(small.task, model=model)
    freeze = bool((cfg.get("experts") or {}).get("freeze", True))
    for modality in needed_experts(cfg):  # stage 2 starts from the experts, as ablate.run.experts.attach loads them
        model.load_expert(modality, instantiate(expert_config(cfg, modality).model), freeze=freeze)
    params = list(task.parameters())
    trainable = [p for p in params if p.requires_grad]
    optimizer = task.optimizer_factory(params=trainable)
    scheduler = None
    if task.scheduler_factory is not None:
        target = getattr(task.scheduler_factory, "func", task.scheduler_factory)
        kwargs = {"total_steps": steps} if "total_steps" in inspect.signature(target).parameters else {}
        scheduler = task.scheduler_factory(optimizer=optimizer, **kwargs)
    task.train()
    step_batch = task.train_corruptions.apply(batch, 0) if task.train_corruptions is not None else batch
    start = time.perf_counter()
    with SavedTensors(params) as saved, FlopCounterMode(display=False) as forward:
        loss = _loss(task.training_step(step_batch, 0))
    forward_s = time.perf_counter() - start
    if not torch.isfinite(loss):
        raise FloatingPointError(f"training loss {float(loss)} at step 0")
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    if scheduler is not None:
        scheduler.step()
    train_s = time.perf_counter() - start
    grads = _nbytes(p.grad for p in trainable if p.grad is not None)
    unused = [n for n, p in task.named_parameters() if p.requires_grad and p.grad is None]
    state = _nbytes(v for s in optimizer.state.values() for v in s.values() if torch.is_tensor(v))
    del loss
    task.eval()
    start = time.perf_counter()
    with torch.no_grad():
        task.on_test_epoch_start()
        task.test_step(test_batch, 0)
        task.on_test_epoch_end()  # the metrics computed (and logged nowhere: no trainer)
    test_s = time.perf_counter() - start
    return {
        "params": sum(p.numel() for p in params),
        "trainable": sum(p.numel() for p in trainable),
        "macs": forward.get_total_flops() // 2,
        "forward_s": forward_s,
        "train_s": train_s,
        "test_s": test_s,
        "data_s": data_s,
        "activations": saved.nbytes,
        "weights": _nbytes(params) + _nbytes(task.buffers()),
        "grads": grads,
        "optimizer_state": state,
        "input": [int(small.data.synth.height), int(small.data.synth.width)],
        "unused": unused,
    }


def gpu_memory(m: dict[str, Any], batch: int) -> float:
    """Estimated GPU memory in bytes of a training step at ``batch`` under bf16-mixed (module docstring)."""
    return (
        m["weights"] + m["grads"] + m["optimizer_state"] + m["activations"] * batch * BF16_ACTIVATIONS + CUDA_OVERHEAD
    )


def gpu_hours(macs: int, frames: int, seeds: int = 1, gpu: Gpu = GPU) -> float:
    """GPU-hours of training on ``frames`` frames (each seed) of a network of ``macs`` MACs a frame: MACs x 2 FLOPs x
    3 (forward + backward) over ``gpu``'s dense bf16 peak x :data:`UTILISATION`."""
    return macs * 2 * 3 * frames * seeds / (gpu.bf16_tflops * 1e12 * UTILISATION) / 3600


def measured_config(experiment: str, row: str, expert: str | None = None, overrides: Iterable[str] = ()) -> DictConfig:
    """The config a row's training runs: its job config; for a single-modal row of a two-stage table, and for an
    ``expert`` of a fused row, the expert's (:func:`ablate.run.experts.expert_config`: the job that trains it)."""
    cfg = job_config(experiment, row, overrides)
    if expert is None and cfg.get("experts") and cfg.stage.name == "single":
        expert = str(cfg.stage.modality)
    return expert_config(cfg, expert) if expert is not None else cfg


def _child(spec: tuple[str, str, str | None], data_dir: str, overrides: list[str]) -> dict[str, Any]:
    """One measurement in a fresh process (:func:`run_isolated`): its figures and its peak RSS."""
    logging.disable(logging.WARNING)
    warnings.filterwarnings("ignore")
    cfg = measured_config(*spec, overrides=overrides)
    out = measure(cfg, sample_config(cfg, data_dir), recipe(cfg)["steps"])
    out["peak_rss"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return out


def run_isolated(spec: tuple[str, str, str | None], data_dir: str, overrides: Iterable[str] = ()) -> dict[str, Any]:
    """:func:`_child` in a fresh (spawned) process: its peak RSS is the row's, and a crash is the row's error."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
        return pool.submit(_child, spec, data_dir, list(overrides)).result()


def cpu_name() -> str:
    """This machine's CPU as ``lscpu`` names it, with its cores."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
        name = fields.get("Model name", "").strip() or hardware.cpu().model
    except (OSError, subprocess.CalledProcessError):
        name = hardware.cpu().model or platform.processor()
    return f"{name} ({hardware.cores()} cores, {hardware.cpu().isa})"


def plan(chosen_experiments: list[str] | None = None, chosen_rows: list[str] | None = None) -> list[tuple[str, str]]:
    """(table, row) of every row of the chosen tables (all by default), limited to ``chosen_rows``."""
    out = []
    for experiment in chosen_experiments or experiments():
        for row in table_rows(experiment):
            if not chosen_rows or row in chosen_rows:
                out.append((experiment, row))
    return out


def family(cfg: DictConfig) -> str:
    """The task family of a job config (instance: SMoE, detection: DGFN, semantic: ChiNet, road: BiFNet)."""
    return str(cfg.task._target_).rsplit(".", 1)[-1].replace("Task", "").lower()


def describe(pairs: Iterable[tuple[str, str]], overrides: Iterable[str] = ()) -> list[dict[str, Any]]:
    """Per (table, row): its family, recipe (:func:`recipe`), the key of what it trains (:func:`measure_key` of
    :func:`measured_config`) and the keys of the experts it starts from, with how to measure each (``specs``:
    key -> (table, row, expert modality or None))."""
    entries = []
    for experiment, row in pairs:
        cfg = job_config(experiment, row, overrides)
        trains = measured_config(experiment, row, overrides=overrides)
        experts = {m: measure_key(expert_config(cfg, m)) for m in needed_experts(cfg)}
        entries.append(
            {
                "table": experiment,
                "row": row,
                "family": family(cfg),
                "key": measure_key(trains),
                "spec": [experiment, row, None],
                "experts": experts,
                "expert_specs": {m: [experiment, row, m] for m in experts},
                **recipe(trains),
                "expert_steps": recipe(cfg)["expert_steps"],
            }
        )
    return entries


def order(entries: list[dict[str, Any]]) -> list[tuple[str, list]]:
    """Every distinct measurement of ``entries`` (rows and the experts they start from) once, as (key, spec): the
    first row of each task family first, then the others in table order, each row's experts before it."""
    firsts, rest, seen, families = [], [], set(), set()
    for e in entries:
        items = [(k, e["expert_specs"][m]) for m, k in e["experts"].items()] + [(e["key"], e["spec"])]
        target = firsts if e["family"] not in families else rest
        families.add(e["family"])
        for key, spec in items:
            if key not in seen:
                seen.add(key)
                target.append((key, spec))
    return firsts + rest


def check(
    entries: list[dict[str, Any]],
    measured: dict[str, Any],
    budget_s: float | None = None,
    overrides: Iterable[str] = (),
    save=lambda measured: None,
    echo=print,
) -> dict[str, Any]:
    """Measure what ``entries`` train (:func:`order`) and is not in ``measured`` (or failed there), each in a
    process of its own, until ``budget_s`` seconds have passed; ``measured`` (key -> figures, or {"error": ...})
    is updated, and handed to ``save`` after each measurement."""
    start = time.perf_counter()
    cpu = cpu_name()
    with tempfile.TemporaryDirectory(prefix="ablate-paper-") as data_dir:
        for key, spec in order(entries):
            if key in measured and "error" not in measured[key]:
                continue
            name = f"{spec[0]}/{spec[1]}" + (f" (expert {spec[2]})" if spec[2] else "")
            if budget_s is not None and time.perf_counter() - start > budget_s:
                echo(f"{name:44s} not run: the time budget of {budget_s / 60:.0f} min is spent")
                continue
            echo(f"{name:44s} running ...")
            try:
                figures = run_isolated(tuple(spec), data_dir, overrides)
            except Exception as err:  # the row's error, reported; the other rows go on
                message = f"{type(err).__name__}: {err}".strip()
                measured[key] = {"error": message, "where": name, "traceback": traceback.format_exc()[-4000:]}
                echo(f"{name:44s} FAILED: {message}")
            else:
                measured[key] = {**figures, "where": name, "cpu": cpu}
                echo(line(name, figures, next(e for e in entries if key in (e["key"], *e["experts"].values()))))
            save(measured)
    return measured


def line(name: str, m: dict, entry: dict) -> str:
    """One measurement's figures, for the terminal."""
    return (
        f"{name:44s} {m['params'] / 1e6:7.1f} M params {m['macs'] / 1e9:8.1f} GMACs  train step {m['train_s']:6.1f} s"
        f"  test step {m['test_s']:6.1f} s  peak RSS {m['peak_rss'] / 2**30:5.1f} GiB  "
        f"GPU mem @{entry['batch']} {gpu_memory(m, entry['batch']) / 2**30:5.1f} GiB"
    )


def row_hours(entry: dict, measured: dict, gpu: Gpu = GPU) -> float | None:
    """GPU-hours of a row's own training, all seeds (None when not measured)."""
    m = measured.get(entry["key"])
    if m is None or "error" in m:
        return None
    return gpu_hours(m["macs"], entry["steps"] * entry["batch"], entry["seeds"], gpu)


def table_hours(entries: list[dict], measured: dict, gpu: Gpu = GPU) -> tuple[float, list[str]]:
    """GPU-hours of a table: its rows' trainings and the experts its fused rows train first (each once; a
    single-modal row of the table is such an expert), all seeds; and the rows or experts not measured."""
    total, missing, experts = 0.0, [], {}
    own = {e["key"] for e in entries}
    for e in entries:
        hours = row_hours(e, measured, gpu)
        if hours is None:
            missing.append(e["row"])
        else:
            total += hours
        for modality, key in e["experts"].items():
            if key not in own and key not in experts:
                experts[key] = (modality, e)
    for key, (modality, e) in experts.items():
        m = measured.get(key)
        if m is None or "error" in m:
            missing.append(f"the {modality} expert")
        else:
            total += gpu_hours(m["macs"], e["expert_steps"] * e["batch"], e["seeds"], gpu)
    return total, missing


def report(record: dict[str, Any]) -> str:
    """``results/paper_scale.md``: every row of every table with its figures, a row not measured saying why."""
    rows, measured = record["rows"], record["measured"]
    gib = 2**30
    out = [
        "# The paper path at `scale=paper`: one training and one test step per row, on the CPU",
        "",
        "Generated by `python -m ablate.check_paper` (ablate/run/paper_check.py, which says how each figure is "
        "measured); not edited by hand. Each row: its job config at `scale=paper` (full-width networks, the "
        "papers' recipes) on generated frames at 375 x 1242, batch 1, fp32, one training step (forward, loss, "
        "backward, optimiser and scheduler step) and one test step with its metrics, in a process of its own. "
        "Rows of several tables with the same model, task and data share one measurement (`measured as`).",
        "",
        f"- CPU of the step times and RSS: {record['cpu']}; the step times are wall times of one step each "
        "on a machine shared with other jobs (their load inflates them).",
        f"- GPU estimates for an {GPU.name} ({GPU.source}), at {UTILISATION:.0%} utilisation: "
        f"{GPU.bf16_tflops * UTILISATION:.0f} TFLOPs sustained. Per table also an "
        + ", ".join(f"{g.name} ({g.source})" for g in OTHER_GPUS)
        + ".",
        "- **GPU mem** at the recipe's batch (`data.batch_size`), bf16-mixed (`trainer=gpu`): fp32 weights + fp32 "
        "gradients + the optimiser state as measured + the tensors saved for backward at batch 1 "
        f"(**act. b1**, fp32) x batch x {BF16_ACTIVATIONS} (bf16) + {CUDA_OVERHEAD / gib:.1f} GiB of CUDA context "
        "and workspace. An estimate, not a measurement.",
        "- **GPU-h**: MACs x 2 x 3 (forward + backward) x the frames trained on (`max_steps` x batch, or epochs x "
        "training frames) x seeds, over the sustained TFLOPs; a two-stage row's experts (stage 1) are counted "
        "once per table. Validation passes are not counted. An estimate, not a measurement.",
        "- **No GPU was available to this check**: the GPU columns are estimates only; no row has been trained "
        "at `scale=paper trainer=gpu` for throughput, memory, utilisation or a loss curve.",
        "",
    ]
    for experiment in sorted({e["table"] for e in rows}):
        entries = [e for e in rows if e["table"] == experiment]
        hours, missing = table_hours(entries, measured)
        others = "; ".join(f"{table_hours(entries, measured, g)[0]:,.1f} on an {g.name}" for g in OTHER_GPUS)
        out += [f"## {experiment}", ""]
        note = f" (not counted, not measured: {', '.join(missing)})" if missing else ""
        out += [
            f"GPU-hours for the table, {entries[0]['seeds']} seeds: **{hours:,.1f}** on an {GPU.name}; {others}{note}.",
            "",
        ]
        out += [
            "| row | params (M) | GMACs | train step (s) | test step (s) | peak RSS (GiB) | act. b1 (GiB) | batch "
            "| GPU mem (GiB) | steps | GPU-h | measured as |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for e in entries:
            m = measured.get(e["key"])
            if m is None:
                out.append(
                    f"| {e['row']} | not run here: the check's time budget on this CPU was spent "
                    "before this row |  |  |  |  |  |  |  |  |  |  |"
                )
                continue
            if "error" in m:
                error = m["error"].replace("|", "\\|").replace("\n", " ")[:300]
                out.append(f"| {e['row']} | **FAILED**: {error} |  |  |  |  |  |  |  |  |  | {m['where']} |")
                continue
            out.append(
                f"| {e['row']} | {m['params'] / 1e6:.1f} | {m['macs'] / 1e9:.1f} | {m['train_s']:.1f} | "
                f"{m['test_s']:.1f} | {m['peak_rss'] / gib:.1f} | {m['activations'] / gib:.2f} | {e['batch']} | "
                f"{gpu_memory(m, e['batch']) / gib:.1f} | {e['steps']:,} | {row_hours(e, measured):,.1f} | "
                f"{m['where']} |"
            )
        out.append("")
        for e in entries:
            if unused := (measured.get(e["key"]) or {}).get("unused"):
                out += [
                    f"{e['row']}: {len(unused)} trainable parameters get no gradient "
                    f"({', '.join(unused[:4])}{', ...' if len(unused) > 4 else ''}); "
                    "trainer=ddp_gpu / ddp_cpu find them (`find_unused_parameters`).",
                    "",
                ]
    return "\n".join(out)


def failed(entries: list[dict], measured: dict) -> list[str]:
    """The rows whose measurement, or one of whose experts', failed."""
    return [
        f"{e['table']}/{e['row']}"
        for e in entries
        if any("error" in measured.get(k, {}) for k in (e["key"], *e["experts"].values()))
    ]


def main(argv: list[str]) -> int:
    """``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=N] [force=true] [key=value ...]``:
    measure the chosen rows (all by default) not measured yet (``force=true``: again), keep the figures in
    ``results/paper_scale.json``, write ``results/paper_scale.md`` for every row of every table; exit 1 when a row
    fails."""
    options, overrides = {}, []
    for arg in argv:
        key, _, value = arg.partition("=")
        if key in ("experiment", "row", "budget_min", "force"):
            options[key] = value
        else:
            overrides.append(arg)
    chosen = [x for x in (options.get("experiment") or "").split(",") if x]
    if unknown := set(chosen) - set(experiments()):
        print(f"error: no experiment {', '.join(sorted(unknown))}; have {', '.join(experiments())}")
        return 2
    rows = [x for x in (options.get("row") or "").split(",") if x]
    everything = describe(plan(), overrides)
    entries = [e for e in everything if (not chosen or e["table"] in chosen) and (not rows or e["row"] in rows)]
    if not entries:
        print("error: no row of the chosen tables is named " + ", ".join(rows))
        return 2
    store = RESULTS / "paper_scale.json"
    record = json.loads(store.read_text()) if store.is_file() else {}
    keys = {k for e in everything for k in (e["key"], *e["experts"].values())}
    measured = {k: v for k, v in record.get("measured", {}).items() if k in keys}  # those of today's configs
    if options.get("force", "false").lower() in ("true", "1", "yes"):
        for e in entries:
            for k in (e["key"], *e["experts"].values()):
                measured.pop(k, None)

    def save(measured: dict) -> None:
        store.parent.mkdir(parents=True, exist_ok=True)
        store.write_text(json.dumps({"cpu": cpu_name(), "measured": measured}, indent=1, sort_keys=True) + "\n")

    budget = float(options["budget_min"]) * 60 if "budget_min" in options else None
    check(entries, measured, budget, overrides, save)
    save(measured)
    path = RESULTS / "paper_scale.md"
    path.write_text(report({"rows": everything, "measured": measured, "cpu": cpu_name()}) + "\n")
    print(path)
    if bad := failed(entries, measured):
        print(f"error: {len(bad)} row(s) failed: {', '.join(bad)}")
        return 1
    return 0
