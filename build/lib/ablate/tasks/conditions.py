"""Sensor corruptions on batches, for any task: the test conditions a trained model is evaluated under, and the
corruptions drawn per weight update in training (DGFN, seed 002 §IV-A).

A *spec* maps a target to a corruption: ``{camera: noise}``, ``{lidar: blank}``, ``{dhi: occlusion}``. Targets are
``camera`` (every camera modality of the batch: rgb, intensity), ``lidar`` (every LiDAR-derived one: sparse_depth,
dense_depth, ddm_jet, dhi, bev) or one modality name. Corruptions are those of
:data:`ablate.data.conditions.CORRUPTIONS` (blank, occlusion, noise, illumination; noise and illumination on the
camera only) or, on 3-channel camera images, a Complex-KITTI condition of
:data:`ablate.data.conditions.CONDITIONS` (night, rain_day, ...). A modality the batch does not hold is left
alone: a camera-only model under ``{lidar: blank}`` sees its normal input. Each frame draws its own box, noise
level or spot from a generator of its own.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from ablate.data.conditions import (
    CAMERA_MODALITIES,
    CAMERA_ONLY,
    CONDITIONS,
    CORRUPTIONS,
    apply_condition,
    apply_corruption,
)
from ablate.data.dataset import LIDAR_DERIVED, MODALITIES

ROLES = {"camera": tuple(sorted(CAMERA_MODALITIES)), "lidar": tuple(sorted(LIDAR_DERIVED))}
#: Corruptions whose result does not depend on the severity (no robustness curve for them).
SEVERITY_FREE = {"blank", "clear"}
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")
_INDEX = {m: k for k, m in enumerate(MODALITIES)}


def parse_spec(spec: Mapping | None, option: str) -> dict[str, str]:
    """``spec`` checked: every target a role or modality, every corruption known and allowed on its target."""
    out = {}
    for target, name in dict(spec or {}).items():
        target, name = str(target), str(name)
        if target not in ROLES and target not in MODALITIES:
            raise ValueError(f"{option}: unknown target {target!r}; valid: {', '.join([*ROLES, *MODALITIES])}")
        camera = target == "camera" or target in CAMERA_MODALITIES
        if name not in CORRUPTIONS and not (name in CONDITIONS and camera):
            raise ValueError(
                f"{option}: unknown corruption {name!r} for {target!r}; valid: "
                f"{', '.join(CORRUPTIONS)}" + (f", {', '.join(CONDITIONS)}" if camera else "")
            )
        if name in CAMERA_ONLY and not camera:
            raise ValueError(f"{option}: {name!r} applies to the camera only, not to {target!r}")
        out[target] = name
    return out


def corrupt(batch: dict, spec: dict[str, str], seed: Sequence[int], severity: float = 1.0) -> dict:
    """A shallow copy of ``batch`` whose targeted modality tensors [B, C, H, W] are corrupted frame by frame.
    Frame i's generator is seeded by ``(*seed, crc32(frame id), k)``, k the index of the modality in
    :data:`ablate.data.dataset.MODALITIES`."""
    if not spec:
        return batch
    out = dict(batch)
    frames = batch.get("frame") or [str(i) for i in range(_batch_size(batch))]
    for target, name in spec.items():
        for m in ROLES.get(target, (target,)):
            x: Any = batch.get(m)  # a batch holds tensors, lists and dicts
            if not torch.is_tensor(x) or x.ndim != 4:
                continue
            if name in CONDITIONS and x.shape[1] != 3:
                raise ValueError(f"condition {name!r} needs a 3-channel camera image; {m!r} has {x.shape[1]}")
            frames_out = []
            for i, frame in enumerate(frames):
                rng = np.random.default_rng([*seed, zlib.crc32(str(frame).encode()), _INDEX[m]])
                arr = x[i].detach().float().cpu().numpy()
                if name in CONDITIONS:
                    arr = apply_condition(name, arr.transpose(1, 2, 0), rng, severity).transpose(2, 0, 1)
                else:
                    arr = apply_corruption(name, arr, rng, m, severity)
                frames_out.append(torch.from_numpy(np.ascontiguousarray(arr)))
            out[m] = torch.stack(frames_out).to(device=x.device, dtype=x.dtype)
    return out


def _batch_size(batch: dict) -> int:
    return next(v.shape[0] for v in batch.values() if torch.is_tensor(v) and v.ndim)


class EvalConditions:
    """The test conditions of a task (``task.eval_conditions``): name -> spec, in order.

    Each condition is tested at severity 1; ``severities`` adds, for each condition whose corruptions depend on
    the severity, one more test per severity, named ``<condition>-s<severity>`` (``rgb_noise-s0.5``), with the
    same boxes and spots scaled (its generator is seeded by the condition's own name): the points of a robustness
    curve. ``pooled``: the name of one more result pooling the conditions at severity 1 (DGFN's "Full": every test
    frame under every condition, one AP over them all). Frames are corrupted alike for every model and seed
    (generators seeded by ``seed``, the condition and the frame), so rows of a table see the same test inputs.
    """

    def __init__(
        self,
        conditions: Mapping[str, Mapping | None],
        severities: Sequence[float] = (),
        pooled: str | None = None,
        seed: int = 0,
    ) -> None:
        option = "task.eval_conditions"
        self.specs = {str(n): parse_spec(s, f"{option}.{n}") for n, s in dict(conditions).items()}
        for name in [*self.specs, *([pooled] if pooled else [])]:
            if not _NAME.match(name) or "-s" in name:
                raise ValueError(
                    f"{option}: condition name {name!r} must be letters, digits, '_', '.', '-' "
                    "without '-s' (kept for severities)"
                )
        if pooled in self.specs:
            raise ValueError(f"task.eval_pooled: {pooled!r} is also a condition of {option}")
        if any(float(s) <= 0 for s in severities):
            raise ValueError(f"task.eval_severities must be > 0, got {list(severities)}")
        self.pooled, self.seed = pooled, int(seed)
        self.severity: dict[str, tuple[str, float]] = {n: (n, 1.0) for n in self.specs}
        for sev in sorted({float(s) for s in severities} - {1.0}):
            for n, spec in self.specs.items():
                if spec and set(spec.values()) - SEVERITY_FREE:
                    self.severity[f"{n}-s{sev:g}"] = (n, sev)

    @property
    def names(self) -> list[str]:
        """Every tested condition: the named ones, then the severity variants."""
        return list(self.severity)

    @property
    def base(self) -> list[str]:
        """The named conditions (severity 1), the ones ``pooled`` pools."""
        return list(self.specs)

    def apply(self, batch: dict, name: str) -> dict:
        base, severity = self.severity[name]
        return corrupt(batch, self.specs[base], (self.seed, zlib.crc32(base.encode())), severity)


class TrainCorruptions:
    """Corruptions drawn per weight update (``task.train_corruptions``), DGFN §IV-A: "for every weight update, we
    try one of above five modifications (including no action) to the training images with equal probability".

    ``choices``: each a spec (``{}`` is no action) or a list of specs, of which one is drawn with equal
    probability. DGFN's blank and occlusion hit "either camera image or Lidar image" without saying how the
    sensor is chosen; ``[{camera: blank}, {lidar: blank}]`` reads it as 50/50. Reading of "to the training
    images": the drawn corruption hits every frame of the batch (of the update), each frame with its own random
    box, noise level or spot. The draw of update ``step`` is seeded by ``(seed, step)``, so a resumed run draws
    as an uninterrupted one, and with gradient accumulation every batch of one update shares its draw.
    """

    def __init__(self, choices: Sequence, seed: int = 0, severity: float = 1.0) -> None:
        option = "task.train_corruptions.choices"
        if not choices:
            raise ValueError(f"{option}: give at least one choice ({{}} is no action)")
        self.choices = [
            [
                parse_spec(s, f"{option}.{i}")
                for s in (c if isinstance(c, Sequence) and not isinstance(c, (str, Mapping)) else [c])
            ]
            for i, c in enumerate(choices)
        ]
        self.seed, self.severity = int(seed), float(severity)

    def draw(self, step: int) -> tuple[dict[str, str], np.random.Generator]:
        """The spec of weight update ``step`` and the generator that drew it."""
        rng = np.random.default_rng([self.seed, int(step)])
        options = self.choices[int(rng.integers(len(self.choices)))]
        return options[int(rng.integers(len(options)))], rng

    def apply(self, batch: dict, step: int) -> dict:
        spec, rng = self.draw(step)
        return corrupt(batch, spec, (self.seed, int(step), int(rng.integers(1 << 30))), self.severity)
