"""A fit's inner state over training (``trace: {every: N}``): how a fused network's gates and branches learn.

Every ``every`` optimiser steps :class:`Trace` logs, as metrics of the job's run at that step:

* ``trace/grad_<part>``: the L2 norm of the gradient of each part of the model, read before the optimiser step
  (after backward): a ``ModuleDict`` child one entry per key (DGFN's trunks: ``trace/grad_branches.rgb``,
  ``trace/grad_branches.dhi``), any other child as one (``trace/grad_fuse``, ``trace/grad_head``).
* ``trace/gate<k>_<modality>``: the mean weight map of fusion point ``k`` (0: the first, DGFN's conv4_3) over the
  step's batch, for an operator that keeps its weight maps (``last_gates``: the GFU, DGFN eq. 6-7), and
  ``trace/gate<k>_<modality>_shut``: the share of its weights below 0.05 (a gate that has closed on that input).

The trace changes no number of the fit (it reads gradients and weight maps the step computes anyway), so ``trace``
is not in the config hash (:data:`ablate.store.identity.UNHASHED`). ``bench/bench_dgfn_spread.py`` reads it.
"""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback
from torch import nn

SHUT = 0.05  # a weight below this has closed its input


def parts(model: nn.Module) -> dict[str, list[nn.Parameter]]:
    """The model's parameters by part: each child, a ``ModuleDict`` child per key (``branches.rgb``)."""
    out: dict[str, list[nn.Parameter]] = {}
    for name, child in model.named_children():
        items = child.items() if isinstance(child, nn.ModuleDict) else [(None, child)]
        for key, module in items:
            params = [p for p in module.parameters() if p.requires_grad]
            if params:
                out[name if key is None else f"{name}.{key}"] = params
    return out


def grad_norms(model: nn.Module) -> dict[str, float]:
    """``{trace/grad_<part>: L2 norm of its gradients}`` over the parts (:func:`parts`) that have gradients."""
    out = {}
    for name, params in parts(model).items():
        grads = [p.grad.detach().float() for p in params if p.grad is not None]
        if grads:
            out[f"trace/grad_{name}"] = float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])))
    return out


def gate_stats(model: nn.Module) -> dict[str, float]:
    """Mean weight map and share shut (< :data:`SHUT`) of each fusion point that keeps its weight maps."""
    ops = model.fusion_modules() if hasattr(model, "fusion_modules") else []
    names = list(getattr(model, "modalities", []))
    out = {}
    for k, op in enumerate(ops):
        gates = getattr(op, "last_gates", None)
        if not gates or not getattr(op, "gated", True):
            continue
        for i, g in enumerate(gates):
            m = names[i] if i < len(names) else str(i)
            g = g.detach().float()
            out[f"trace/gate{k}_{m}"] = float(g.mean())
            out[f"trace/gate{k}_{m}_shut"] = float((g < SHUT).float().mean())
    return out


class Trace(Callback):
    """Log :func:`grad_norms` before every ``every``-th optimiser step and :func:`gate_stats` after its batch."""

    def __init__(self, every: int = 10) -> None:
        if int(every) < 1:
            raise ValueError(f"trace.every: {every} must be an integer >= 1")
        self.every = int(every)

    def _due(self, trainer: L.Trainer) -> bool:
        return trainer.global_step % self.every == 0

    def on_before_optimizer_step(self, trainer: L.Trainer, pl_module: L.LightningModule, optimizer: Any) -> None:
        if self._due(trainer) and trainer.logger is not None:
            trainer.logger.log_metrics(grad_norms(pl_module.model), step=trainer.global_step)

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        step = trainer.global_step - 1  # the step this batch took
        if step % self.every == 0 and trainer.logger is not None:
            trainer.logger.log_metrics(gate_stats(pl_module.model), step=step)
