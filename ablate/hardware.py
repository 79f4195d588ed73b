"""The machine a job runs on, and the numerics it trains with: precision, memory format, threads, compilation.

The CPUs that run this project differ. On one with bf16 in hardware (AMX, or AVX-512 BF16) bf16 autocast with
channels_last tensors trains the ChiNet family about 2.5x faster than fp32; on one with AVX2 only, bf16 autocast is
emulated and 9-33x slower, and channels_last alone gains 7-13 % on some families and loses 12 % on ChiNet
(``bench/bench_precision.py``; docs/numerics.md). So the precision follows the hardware:
``trainer.precision: auto`` is resolved when a job starts (:func:`resolve`), and the resolved value, never
``auto``, goes into the job's config, its config hash, its params and its tags.

The trainer options read here (conf/trainer/default.yaml), beside Lightning's own:

* ``precision``: Lightning's (``32-true``, ``bf16-mixed``, ...), or ``auto``: ``bf16-mixed`` where the CPU has bf16
  in hardware *and* the task family's recipe takes it (``recipe.bf16: true``: its bf16 parity with fp32 measured,
  and a job gaining enough for the halved race budget), else ``32-true``. On a GPU (``trainer=gpu``, ``ddp_gpu``)
  it is ``bf16-mixed``, set in their configs.
* ``channels_last``: the model's memory format; ``auto`` follows the precision (channels_last with bf16).
* ``compile``: ``torch.compile`` the model in place, so that checkpoints keep their keys: ``true`` (inductor) or a
  backend's name.
* ``threads``: the job's intra-op threads (``torch.set_num_threads``); results depend on it (a reduction split over
  two threads adds in another order), so it is config and in the hash. ``null``: torch's default, every core.

Losses, metric accumulation, NMS scores and BatchNorm statistics stay in fp32 under bf16 autocast: a task's model
outputs are cast to fp32 before anything reads them (:func:`ablate.tasks.base.FusionTask.forward`), and BatchNorm
keeps fp32 running statistics and weights.
"""

from __future__ import annotations

import os
import platform
import warnings
from copy import deepcopy
from dataclasses import dataclass
from functools import lru_cache

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import ValidationError

#: CPU flags (``/proc/cpuinfo``) that mean bf16 arithmetic in hardware.
BF16_FLAGS = ("amx_bf16", "avx512_bf16")
#: The ISA flags a run's tags and the benchmarks name.
ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")
#: The trainer options that are not the Lightning Trainer's (read here, taken out before it is built).
OPTIONS = ("channels_last", "compile", "threads")
#: Precisions that are bf16 autocast.
BF16 = ("bf16-mixed", "bf16")


@dataclass(frozen=True)
class Cpu:
    """What a job needs to know of the CPU: its model name and ISA flags."""

    model: str
    flags: frozenset[str]

    @property
    def has_bf16(self) -> bool:
        """bf16 in hardware: AMX or AVX-512 BF16."""
        return any(flag in self.flags for flag in BF16_FLAGS)

    @property
    def isa(self) -> str:
        """The ISA flags that matter for training speed, space-separated (``avx2 avx512f avx512_bf16``)."""
        return " ".join(f for f in ISA_FLAGS if f in self.flags) or "none of " + "/".join(ISA_FLAGS)


@lru_cache(maxsize=1)
def cpu() -> Cpu:
    """This machine's CPU, read from ``/proc/cpuinfo`` (Linux); elsewhere the platform's name and no flags."""
    flags: frozenset[str]
    model, flags = platform.processor() or platform.machine(), frozenset()
    family = number = ""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key == "cpu family":
                    family = value.strip()
                elif key == "model":
                    number = value.strip()
                elif key == "flags":
                    flags = frozenset(value.split())
                if key == "flags" and model:
                    break
    except OSError:
        pass
    if family and number:  # a virtual machine's name ("AMD EPYC") hides the generation: two EPYCs differ in ISA
        model = f"{model} (family {family}, model {number})"
    return Cpu(model, flags)


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def parallel_jobs(threads: int | None, devices: int | str = 1, accelerator: str = "cpu") -> int:
    """Config resolver ``${parallel_jobs:${trainer.threads},${trainer.devices},${trainer.accelerator}}``: how many
    jobs of a sweep run at once on this machine. On the CPU one per ``threads`` x ``devices`` cores (a DDP job's
    processes each take its threads), and one at a time where a job takes every core (``threads`` null, or
    ``devices`` -1 / auto); on a GPU one at a time (set ``hydra.launcher.n_jobs`` for more)."""
    if str(accelerator) in ("gpu", "cuda") or not threads:
        return 1
    processes = int(devices) if isinstance(devices, int) or str(devices).isdigit() else 0
    return max(1, cores() // (int(threads) * processes)) if processes > 0 else 1


def loader_workers(at_most: int = 8) -> int:
    """Config resolver ``${loader_workers:8}``: data loader worker processes, one per core this process may use and
    at most ``at_most`` (``min(8, cores)`` at ``scale=paper``): more workers than cores only contend for them."""
    return max(1, min(int(at_most), cores()))


def _on_gpu(trainer: DictConfig) -> bool:
    return str(trainer.get("accelerator", "auto")) in ("gpu", "cuda")


def check(trainer: DictConfig) -> None:
    """Raise a ValidationError naming ``trainer.threads`` or ``trainer.channels_last`` when its value is not one
    these options take."""
    threads = trainer.get("threads")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValidationError(
            f"trainer.threads={threads!r}: expected a whole number of threads >= 1, or null "
            "(torch's default: every core)"
        )
    channels_last = trainer.get("channels_last", "auto")
    if channels_last != "auto" and not isinstance(channels_last, bool):
        raise ValidationError(f"trainer.channels_last={channels_last!r}: expected true, false or auto")


def resolve(cfg: DictConfig, machine: Cpu | None = None, quiet: bool = False) -> str:
    """Resolve ``trainer.precision`` and ``trainer.channels_last`` in place (``auto`` -> a value); return why, in
    one sentence for the job's log. An explicit bf16 precision on a CPU without bf16 in hardware warns (once),
    unless ``quiet``. A config without a trainer is left as it is."""
    machine = machine or cpu()
    trainer = cfg.get("trainer")
    if not isinstance(trainer, DictConfig):
        return "no trainer"
    check(trainer)
    precision = str(trainer.get("precision", "32-true"))
    family_ok = bool(OmegaConf.select(cfg, "recipe.bf16", default=False))
    if precision != "auto":
        why = f"precision {precision} as configured"
        if precision in BF16 and not _on_gpu(trainer) and not machine.has_bf16 and not quiet:
            warnings.warn(
                f"trainer.precision={precision} on a CPU without bf16 in hardware ({machine.model}: "
                f"{machine.isa}): bf16 is emulated there and training is far slower (about 30x); "
                "trainer.precision=auto chooses fp32 on such a CPU",
                stacklevel=2,
            )
    elif _on_gpu(trainer):
        precision, why = "bf16-mixed", "precision bf16-mixed: a GPU"
    elif machine.has_bf16 and family_ok:
        precision, why = "bf16-mixed", f"precision bf16-mixed: {machine.model} has {machine.isa}"
    elif machine.has_bf16:
        precision = "32-true"
        why = (
            "precision 32-true: the CPU has bf16, but this task family's recipe keeps fp32 (recipe.bf16 is not true: "
            "its bf16 parity is not measured, or bf16 does not pay for it; its recipe file says which)"
        )
    else:
        precision = "32-true"
        why = f"precision 32-true: {machine.model} has no bf16 in hardware ({machine.isa})"
    channels_last = trainer.get("channels_last", "auto")
    if channels_last == "auto":
        channels_last = precision in BF16
        why += f"; channels_last {'on' if channels_last else 'off'} (follows the precision)"
    with open_dict(cfg):
        trainer.precision = precision
        trainer.channels_last = bool(channels_last)
    return why


def resolved(cfg: DictConfig) -> DictConfig:
    """A copy of ``cfg`` with its numerics resolved for this machine (``cfg`` itself when nothing is ``auto``)."""
    trainer = cfg.get("trainer")
    if not isinstance(trainer, DictConfig) or "auto" not in (trainer.get("precision"), trainer.get("channels_last")):
        return cfg
    copy = deepcopy(cfg)
    resolve(copy, quiet=True)
    return copy


def gpu(trainer: DictConfig) -> str | None:
    """The name of the CUDA device a job of ``trainer`` trains on (``trainer=gpu``: its first device, as torch
    names it), or None where it trains on the CPU."""
    import torch  # here: the config's resolvers run without torch

    if not _on_gpu(trainer) or not torch.cuda.is_available():
        return None
    return torch.cuda.get_device_name(0)


def kernels() -> str:
    """The CPU kernels torch runs here: ATen's instruction set (``ATEN_CPU_CAPABILITY`` selects a lower one on any
    machine) and oneDNN's cap where ``ONEDNN_MAX_CPU_ISA`` sets one (``AVX512``, ``AVX2; oneDNN AVX2``): results
    follow them as they follow the CPU."""
    import torch

    ours = str(torch.backends.cpu.get_cpu_capability())
    onednn = os.environ.get("ONEDNN_MAX_CPU_ISA", "")
    return ours + (f"; oneDNN {onednn}" if onednn else "")


def tags(cfg: DictConfig) -> dict[str, str]:
    """The numerics and the machine, as run tags: resolved precision, memory format, threads, compile, CPU, ISA,
    the CPU kernels in use (:func:`kernels`), and the GPU (tag ``gpu``) where the job trains on one."""
    machine = cpu()
    trainer = cfg.trainer
    device = gpu(trainer)
    return {
        "precision": str(trainer.get("precision")),
        "channels_last": str(trainer.get("channels_last")),
        "threads": str(trainer.get("threads")),
        "compile": str(trainer.get("compile", False)),
        "cpu": machine.model,
        "cpu_isa": machine.isa,
        "cpu_kernels": kernels(),
        **({"gpu": device} if device else {}),
    }


def race_budget(bf16_min: float, fp32_min: float, *, _root_: DictConfig) -> float:
    """``${race_budget:60,120}``: a table race's wall-time budget in minutes (``scale.race.budget_min``),
    ``bf16_min`` where the table's jobs resolve to bf16 on this machine, else ``fp32_min``: bf16 trains the
    families whose parity holds about 2.5x faster, so their tables race in half the time."""
    precision = OmegaConf.select(resolved(_root_), "trainer.precision", default="32-true")
    return float(bf16_min if precision in BF16 else fp32_min)


def register_resolvers() -> None:
    """The config resolvers this module serves (idempotent)."""
    if not OmegaConf.has_resolver("race_budget"):
        OmegaConf.register_new_resolver("race_budget", race_budget)
    if not OmegaConf.has_resolver("parallel_jobs"):
        OmegaConf.register_new_resolver("parallel_jobs", parallel_jobs)
    if not OmegaConf.has_resolver("loader_workers"):
        OmegaConf.register_new_resolver("loader_workers", loader_workers)
