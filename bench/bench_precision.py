"""Training step and inference of each task family's real model at the cpu scale, in every numerics variant:
fp32, channels_last, bf16 autocast, bf16 + channels_last, and torch.compile (inductor; its compile time apart).

    PYTHONPATH=. python bench/bench_precision.py [--families chinet,dgfn] [--threads 1,2] [--steps 3]
        [--variants fp32,channels_last,bf16,bf16+channels_last,compile] [--bf16 once|full|skip]
        [--set data.synth.height=256 data.synth.width=832 ...]

The families: the SMoE expert (RGB, YOLACT head) and the fused FPN model of stage 2 (SMoE on its two experts, no
feature cache); DGFN (GFU, SSD); ChiNet; BiFNet with DST and CBF. Each is built from its table's config at
``scale=cpu`` (``ablate.hardware``'s options untouched), with real batches of generated frames at the cpu scale's
resolution and batch size. A training step is forward (under autocast for bf16), the task's loss, backward and the
optimiser's step; inference is one forward pass at batch 1 without gradients, as the tables' latency. Variants are
interleaved step by step in one process, so load on the machine slows them alike; figures are medians.

Prints the CPU model and its ISA flags, then per family and thread count the median time, the speed-up over fp32,
and the achieved GFLOP/s (2 x MACs of one forward pass per frame, x3 for a training step: forward and backward).

On a CPU without bf16 in hardware bf16 autocast is emulated and about 30x slower: there the bf16 variants are timed
for one step at batch 1 only, beside fp32 at batch 1 (``--bf16 full`` times them in full anyway, ``skip`` not at
all).
"""

from __future__ import annotations

import argparse
import copy
import math
import os
import statistics
import tempfile
import time
import warnings
from contextlib import nullcontext
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ablate.analysis.latency import macs
from ablate.hardware import cpu
from ablate.jobs.experts import expert_config, needed

warnings.filterwarnings("ignore")
CONF = Path(__file__).resolve().parents[1] / "conf"
#: family -> overrides that compose its job (and, for the SMoE expert, the modality whose expert it is).
FAMILIES = {
    "smoe_expert": ["fusion=smoe"],
    "smoe_fpn": ["fusion=smoe"],
    "dgfn": ["experiment=dgfn_table1", "row=dgfn"],
    "chinet": ["experiment=chinet_table2", "row=chinet"],
    "bifnet_dst": ["experiment=bifnet_table4", "row=bifnet_dst_cbf"],
}
VARIANTS = ("fp32", "channels_last", "bf16", "bf16+channels_last", "compile")
FRAMES = 20  # generated frames: the training split's 60 % gives one batch of 8


def build(family: str, extra: tuple[str, ...] = ()):
    """(task, a training batch, the config) of ``family`` at the cpu scale with the Hydra overrides ``extra`` on
    top (another resolution, say), its frames generated under ``data/``."""
    overrides = [*FAMILIES[family], "scale=cpu", *extra, f"data.synth.frames={FRAMES}", "data.num_workers=0"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    if family == "smoe_expert":
        cfg = expert_config(cfg, "rgb")
    torch.manual_seed(0)
    model = instantiate(cfg.model)
    if cfg.get("experts") and cfg.stage.get("name") != "single":
        for modality in needed(cfg):  # random experts: their cost, not their weights, is measured
            model.load_expert(
                modality, instantiate(expert_config(cfg, modality).model), freeze=cfg.experts.get("freeze", True)
            )
    task = instantiate(cfg.task, model=model)
    task.log = lambda *args, **kwargs: None  # training_step outside a Trainer
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    batch = next(iter(datamodule.train_dataloader()))
    return task, batch, cfg


def job_steps(cfg) -> int:
    """Training steps of the family's job at the cpu scale: epochs x batches of the training split (60 % of the
    scale's frames, or its ``data.limit_frames.train``); the SMoE expert's config carries the recipe's
    ``experts.max_epochs`` (stage 1, ``expert_config``)."""
    frames = OmegaConf.load(CONF / "scale" / "cpu.yaml").data.synth.frames
    train = OmegaConf.select(cfg, "data.limit_frames.train", default=None) or round(0.6 * frames)
    return int(cfg.trainer.max_epochs) * math.ceil(train / int(cfg.data.batch_size))


def first(batch: dict, n: int) -> dict:
    """The first ``n`` frames of ``batch``."""
    return {k: v[:n] if torch.is_tensor(v) or isinstance(v, (list, tuple)) else v for k, v in batch.items()}


def channels_last(batch: dict) -> dict:
    return {
        k: v.contiguous(memory_format=torch.channels_last) if torch.is_tensor(v) and v.ndim == 4 else v
        for k, v in batch.items()
    }


class Variant:
    """One numerics variant of a family's task: its own copy of the model and optimiser."""

    def __init__(self, name: str, task, batch: dict) -> None:
        self.name = name
        self.task = copy.deepcopy(task)
        self.task.log = lambda *args, **kwargs: None
        self.cl = "channels_last" in name
        if self.cl:
            self.task.to(memory_format=torch.channels_last)
        self.bf16 = name.startswith("bf16")
        self.batch = channels_last(batch) if self.cl else batch
        self.optimizer = self.task.optimizer_factory(params=self.task.trainable())
        self.compile_s = {}
        if name == "compile":
            self.task.model.compile()

    def autocast(self):
        return torch.autocast("cpu", dtype=torch.bfloat16) if self.bf16 else nullcontext()

    def train_step(self, batch: dict | None = None) -> float:
        batch = batch if batch is not None else self.batch
        self.task.train()
        t0 = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        with self.autocast():
            loss = self.task.training_step(batch, 0)
        loss.backward()
        self.optimizer.step()
        return time.perf_counter() - t0

    def infer(self, sample: dict) -> float:
        self.task.eval()
        t0 = time.perf_counter()
        with torch.no_grad(), self.autocast():
            self.task(sample)
        return time.perf_counter() - t0


def bench(
    family: str,
    threads: int,
    steps: int,
    bf16_mode: str,
    has_bf16: bool,
    wanted: tuple[str, ...] = VARIANTS,
    extra: tuple[str, ...] = (),
) -> None:
    torch.set_num_threads(threads)
    task, batch, cfg = build(family, extra)
    sample = first(batch, 1)
    n = len(batch.get("frame", [])) or next(v.shape[0] for v in batch.values() if torch.is_tensor(v))
    task.eval()
    mac = macs(task.model, {k: v for k, v in sample.items()})
    slow_bf16 = not has_bf16 and bf16_mode != "full"
    names = [v for v in VARIANTS if v in wanted or v == "fp32"]
    names = [v for v in names if not (v.startswith("bf16") and (slow_bf16 or bf16_mode == "skip"))]
    variants = [Variant(name, task, batch) for name in names]
    train: dict[str, list[float]] = {v.name: [] for v in variants}
    infer: dict[str, list[float]] = {v.name: [] for v in variants}
    first_train, first_infer, failed = {}, {}, {}
    for v in list(variants):  # warm-up; compile's first calls are its compile time
        try:
            first_train[v.name] = v.train_step()
            first_infer[v.name] = v.infer(channels_last(sample) if v.cl else sample)
        except Exception as err:  # torch.compile can fail on a model: say so and time the others
            failed[v.name] = f"{type(err).__name__}: {str(err).splitlines()[0][:160]}"
            variants.remove(v)
            del train[v.name], infer[v.name]
    for i in range(steps):
        order = variants[i % len(variants) :] + variants[: i % len(variants)]
        for v in order:
            train[v.name].append(v.train_step())
            infer[v.name].append(v.infer(channels_last(sample) if v.cl else sample))
    params = sum(p.numel() for p in task.model.parameters()) / 1e6
    print(
        f"\n{family}: batch {n} at {cfg.data.synth.height}x{cfg.data.synth.width}, {params:.2f} M params, "
        f"{mac / 1e9:.2f} GMACs per frame (forward), {threads} thread(s), median of {steps}"
    )
    print(
        f"  {'variant':<20} {'train step':>11} {'speed-up':>9} {'GFLOP/s':>8}   {'inference':>10} {'speed-up':>9} "
        f"{'GFLOP/s':>8}"
    )
    base_t, base_i = statistics.median(train["fp32"]), statistics.median(infer["fp32"])
    for v in variants:
        t, f = statistics.median(train[v.name]), statistics.median(infer[v.name])
        print(
            f"  {v.name:<20} {t:9.3f} s {base_t / t:8.2f}x {6 * mac * n / t / 1e9:8.1f}   {1000 * f:7.1f} ms "
            f"{base_i / f:8.2f}x {2 * mac / f / 1e9:8.1f}"
        )
    for name, error in failed.items():
        print(f"  {name:<20} failed: {error}")
    steps_per_job = job_steps(cfg)
    print(
        f"  a cpu-scale job's {steps_per_job} training steps at these medians: "
        + ", ".join(f"{v.name} {steps_per_job * statistics.median(train[v.name]) / 60:.1f} min" for v in variants)
        + " (training only: no validation, test or data generation)"
    )
    if "compile" in train:
        compile_s = first_train["compile"] - statistics.median(train["compile"])
        net = steps_per_job * (base_t - statistics.median(train["compile"])) - compile_s
        print(
            f"  compile time: {compile_s:.1f} s (training), "
            f"{first_infer['compile'] - statistics.median(infer['compile']):.1f} s (inference); over a cpu-scale "
            f"job's {steps_per_job} training steps compile {'saves' if net > 0 else 'costs'} {abs(net):.0f} s"
        )
    if slow_bf16 and bf16_mode == "once" and any(v.startswith("bf16") for v in wanted):
        one = first(batch, 1)
        fp32, bf16 = Variant("fp32", task, one), Variant("bf16", task, one)
        fp32.train_step(), bf16.train_step()  # warm-up: one step each
        t32, t16 = fp32.train_step(), bf16.train_step()
        print(
            f"  bf16 autocast, no bf16 in hardware: one training step at batch 1 takes {t16:.2f} s against "
            f"{t32:.2f} s in fp32 ({t16 / t32:.1f}x slower); not timed at full batch"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default=",".join(FAMILIES), help="comma-separated: " + ", ".join(FAMILIES))
    parser.add_argument("--threads", default="1,2", help="comma-separated intra-op thread counts")
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help="comma-separated: " + ", ".join(VARIANTS) + " (fp32, the baseline, always runs)",
    )
    parser.add_argument("--steps", type=int, default=3, help="timed steps per variant, after one warm-up step")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="Hydra overrides on top of each family's config, e.g. data.synth.height=256 data.synth.width=832",
    )
    parser.add_argument(
        "--bf16",
        choices=("once", "full", "skip"),
        default="once",
        help="bf16 variants on a CPU without bf16 in hardware: one step at batch 1 (once), in full, or not at all",
    )
    args = parser.parse_args()
    machine = cpu()
    print(
        f"CPU: {machine.model}; {os.cpu_count()} cores; ISA: {machine.isa}; bf16 in hardware: "
        f"{'yes' if machine.has_bf16 else 'no'}; torch {torch.__version__}, "
        f"{torch.backends.cpu.get_cpu_capability()} kernels"
    )
    with tempfile.TemporaryDirectory() as scratch:  # the generated frames
        here = os.getcwd()
        os.chdir(scratch)
        try:
            for family in args.families.split(","):
                for threads in (int(t) for t in args.threads.split(",")):
                    bench(
                        family,
                        threads,
                        args.steps,
                        args.bf16,
                        machine.has_bf16,
                        tuple(args.variants.split(",")),
                        tuple(args.set),
                    )
        finally:
            os.chdir(here)


if __name__ == "__main__":
    main()
