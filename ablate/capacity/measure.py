"""One row of the paper check measured (:mod:`ablate.capacity.check`): one training step and one test step of its
config at ``scale=paper``, at batch 1, on the CPU in fp32, in the calling process.

- The data (:func:`sample_config`): :data:`FRAMES` frames of the generated dataset at the paper's resolution
  (``data.synth`` height and width of ``conf/scale/paper.yaml``: KITTI's 375 x 1242), batch 1, no loader workers;
  the data module as configured otherwise (BiFNet's paper augmentation included).
- The model and task (:func:`ablate.jobs.steptime.build`) built with hydra's ``instantiate`` as :mod:`ablate.jobs.job` does, with the
  frozen experts of a two-stage row (SMoE §4.3; BiFNet §V-B) loaded into the fused model from freshly built experts
  (``load_expert`` with ``experts.freeze``), so that what is frozen is what a job freezes.
- One training step (the row's training corruptions, forward, loss, backward, the recipe's optimiser and scheduler
  step), then one test step with the task's test conditions, its metrics computed.

Figures (:func:`measure`): parameters; MACs of the training step's forward pass (``FlopCounterMode``: convolutions
and matrix products, MACs = FLOPs / 2, as :func:`ablate.analysis.latency.macs` counts them), and of them those run in
frozen parts (:class:`FrozenMacs`: the frozen experts); the bytes of one frame's frozen expert features (what a
feature cache, :class:`ablate.jobs.experts.FeatureCache`, holds of a frame); the training and test steps' wall times
on this CPU; the bytes of the tensors saved for backward at batch 1 (:class:`SavedTensors`: each storage counted
once, the parameters left out): the activation memory; the weights, gradients and optimiser state after the step;
the trainable parameters that got no gradient (``unused``: DDP needs ``find_unused_parameters`` for them,
conf/trainer/ddp_*.yaml). :func:`count_macs` counts the MACs alone (no backward, nothing timed).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any, cast

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from ablate.jobs.steptime import build as _build

#: Frames of generated data each row reads (one training, one test frame after the 60/20/20 split).
FRAMES = 2


def sample_config(
    cfg: DictConfig, data_dir: str, size: tuple[int, int] | None = None, frames: int = FRAMES
) -> DictConfig:
    """``cfg`` resolved, on ``frames`` generated frames under ``data_dir`` at the config's own resolution (or
    ``size``, height x width), batch 1, no loader workers; the data module's other options (augmentation, BEV grid,
    conditions) as configured."""
    small = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    with open_dict(small):
        synth = dict(small.data.get("synth") or {})
        height, width = size or (int(synth.get("height", 375)), int(synth.get("width", 1242)))
        small.data.root = None
        small.data.synth = {**synth, "frames": frames, "seed": 0, "height": height, "width": width}
        small.data.data_dir = data_dir
        small.data.batch_size = 1
        small.data.num_workers = 0
        small.data.limit_frames = None
    return cast(DictConfig, small)


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


class FrozenMacs:
    """MACs run inside a model's frozen parts while active: the outermost submodules whose parameters are all
    frozen (``requires_grad`` False: the experts :meth:`load_expert` froze), called on inputs that need no gradient,
    each call counted by a ``FlopCounterMode`` of its own between forward hooks (the outer counter counts them too).
    A frozen part on the gradient's path (an input that needs a gradient) still runs backward for that gradient,
    so it is not counted here: it costs what a trainable part costs, an over-estimate of its weights' gradients."""

    def __init__(self, model: torch.nn.Module) -> None:
        self.macs, self._depth, self._counter = 0, 0, None
        self.parts = frozen_parts(model)
        self._handles: list[Any] = []

    def _enter(self, module: torch.nn.Module, args: Any) -> None:
        if self._depth == 0 and not any(t.requires_grad for t in _tensors(args)):
            counter = FlopCounterMode(display=False)
            counter.__enter__()
            self._counter = counter
        self._depth += 1

    def _exit(self, *_: Any) -> None:
        self._depth -= 1
        if self._depth == 0 and self._counter is not None:
            self._counter.__exit__(None, None, None)
            self.macs += self._counter.get_total_flops() // 2
            self._counter = None

    def __enter__(self) -> FrozenMacs:
        for part in self.parts:
            self._handles += [part.register_forward_pre_hook(self._enter), part.register_forward_hook(self._exit)]
        return self

    def __exit__(self, *exc: object) -> None:
        for handle in self._handles:
            handle.remove()
        self._handles = []


def _tensors(tree: Any) -> Iterable[torch.Tensor]:
    """The tensors of nested tuples, lists and dicts."""
    if torch.is_tensor(tree):
        yield tree
    elif isinstance(tree, (list, tuple)):
        for item in tree:
            yield from _tensors(item)
    elif isinstance(tree, dict):
        for item in tree.values():
            yield from _tensors(item)


def frozen_parts(model: torch.nn.Module) -> list[torch.nn.Module]:
    """The outermost submodules of ``model`` that have parameters, all of them frozen (containers that are never
    called, ``ModuleList`` and ``ModuleDict``, left for their members)."""
    parts: list[torch.nn.Module] = []
    inside: set[str] = set()
    for name, module in model.named_modules():
        if any(name.startswith(p + ".") for p in inside) or isinstance(module, (nn.ModuleList, nn.ModuleDict)):
            continue
        params = list(module.parameters())
        if params and not any(p.requires_grad for p in params):
            parts.append(module)
            inside.add(name)
    return parts


def _features(task: Any) -> int:
    """Bytes of one frame's frozen expert features in the task's feature cache (0 without one), which stores the
    features of the frames it has seen: one here."""
    cache = task.feature_cache
    return int(cache.nbytes // max(1, len(cache.frames))) if cache is not None else 0


def count_macs(cfg: DictConfig, small: DictConfig) -> dict[str, Any]:
    """The MACs of job config ``cfg``'s training forward pass on a frame of ``small`` and those of them in frozen
    parts (:class:`FrozenMacs`), with the bytes of a frame's frozen features: :func:`measure`'s counts without its
    step (no backward, nothing timed)."""
    built = _build(cfg, small)
    task = built["task"]
    with FrozenMacs(built["model"]) as frozen, FlopCounterMode(display=False) as forward:
        _loss(task.training_step(built["batch"], 0))  # with autograd on, as a step: what needs gradients is seen
    return {"macs": forward.get_total_flops() // 2, "macs_frozen": frozen.macs, "feature_bytes": _features(task)}


def measure(cfg: DictConfig, small: DictConfig, steps: int = 1000) -> dict[str, Any]:
    """One training and one test step of job config ``cfg`` on the frames of ``small`` (:func:`sample_config`), in
    this process: the figures of the module's docstring (times in s, memory in bytes). ``steps``: the schedule's
    length the scheduler is built for."""
    built = _build(cfg, small)
    task, model, batch = built["task"], built["model"], built["batch"]
    params = list(task.parameters())
    trainable = task.trainable()
    optimizer, scheduler = task.optimizers_for(trainable, steps)
    start = time.perf_counter()
    with SavedTensors(params) as saved, FrozenMacs(model) as frozen, FlopCounterMode(display=False) as forward:
        loss = _loss(task.training_step(batch, 0))
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
    features = _features(task)
    task.feature_cache = None  # a job tests the whole model, whatever its data
    del loss
    task.eval()
    start = time.perf_counter()
    with torch.no_grad():
        task.on_test_epoch_start()
        task.test_step(built["test_batch"], 0)
        task.on_test_epoch_end()  # the metrics computed (and logged nowhere: no trainer)
    test_s = time.perf_counter() - start
    return {
        "params": sum(p.numel() for p in params),
        "trainable": sum(p.numel() for p in trainable),
        "macs": forward.get_total_flops() // 2,
        "macs_frozen": frozen.macs,
        "feature_bytes": features,
        "forward_s": forward_s,
        "train_s": train_s,
        "test_s": test_s,
        "data_s": built["data_s"],
        "activations": saved.nbytes,
        "weights": _nbytes(params) + _nbytes(task.buffers()),
        "grads": grads,
        "optimizer_state": state,
        "input": [int(small.data.synth.height), int(small.data.synth.width)],
        "unused": unused,
    }
