"""Fusion stages: where in a ResNet + FPN + task-head network the modalities meet (SMoE §5.2, Fig. 5).

| stage      | network                                                                                |
|------------|----------------------------------------------------------------------------------------|
| early      | inputs concatenated on channels -> one ResNet -> FPN -> head (the operator is unused)  |
| backbone   | one ResNet per modality; C3, C4, C5 each fused by its own operator -> one FPN -> head  |
| fpn        | ResNet + FPN per modality (the experts); P3..P7 each fused by its own operator -> head |
| late       | ResNet + FPN + head per modality; every head output map fused by its own operator      |
| single     | one named modality: ResNet -> FPN -> head                                              |

The order of ``modalities`` is the operators' input order: the first is f_i (camera), the second f_j (LiDAR).
The head never sees the stage: it is called as ``head(in_channels=fpn_channels, num_levels=5)`` and its
``forward(list[P3..P7]) -> dict[str, Tensor | list[Tensor]]`` matches its ``out_channels`` dict.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from ablate.fusion.ops import FusionOp
from ablate.nn.fpn import FPN
from ablate.nn.frozen import FreezableModel
from ablate.nn.resnet import ResNet

STAGES = ("early", "backbone", "fpn", "late", "single")
NUM_LEVELS = 5  # P3..P7
BACKBONE_KEYS = ("depth", "width", "weights")


class FusionModel(FreezableModel):
    """A task network whose modalities are fused at ``stage`` by the operator ``fusion`` builds.

    ``fusion``: called as ``fusion(channels=C, num_inputs=N)`` (a partial of ``ablate.fusion.build``);
    unused by ``early`` and ``single``. ``backbone``: ResNet options ``depth`` (18/34/50/101), ``width``,
    ``weights`` (a local file for every encoder, or a dict modality -> file). ``single``: the modality of
    stage ``single`` (may be left out when ``modalities`` has one entry).
    Per-modality parts are ``encoders[m]`` (all stages but early), ``fpns[m]`` (fpn, late), ``heads[m]`` (late).
    """

    def __init__(
        self,
        stage: str,
        modalities: Mapping[str, int],
        fusion: Callable[..., nn.Module] | None = None,
        head: Callable[..., nn.Module] | None = None,
        backbone: Mapping | None = None,
        fpn_channels: int = 64,
        single: str | None = None,
    ) -> None:
        super().__init__()
        if stage not in STAGES:
            raise ValueError(f"unknown fusion stage {stage!r}; valid: {', '.join(STAGES)}")
        if head is None:
            raise ValueError("FusionModel needs `head`: called as head(in_channels=..., num_levels=5)")
        modalities = {str(k): int(v) for k, v in dict(modalities).items()}
        backbone = dict(backbone or {})
        if bad := sorted(set(backbone) - set(BACKBONE_KEYS)):
            raise ValueError(f"unknown backbone option(s) {bad}; valid: {list(BACKBONE_KEYS)}")
        if stage == "single":
            single = single if single is not None else (next(iter(modalities)) if len(modalities) == 1 else None)
            if single not in modalities:
                raise ValueError(f"stage 'single' needs `single` set to one of {list(modalities)}, got {single!r}")
            modalities = {single: modalities[single]}
        elif len(modalities) < 2:
            raise ValueError(f"stage {stage!r} fuses >= 2 modalities, got {list(modalities)}")
        if stage in ("backbone", "fpn", "late") and fusion is None:
            raise ValueError(f"stage {stage!r} needs a fusion operator (`fusion`)")
        self.stage, self.modalities = stage, modalities
        self.single = single if stage == "single" else None
        self.backbone_options, self.fpn_channels = backbone, fpn_channels
        n = len(modalities)
        self.encoders = nn.ModuleDict()
        if stage == "early":
            self.encoder = self._resnet(sum(modalities.values()), None)
        else:
            self.encoders.update({m: self._resnet(c, m) for m, c in modalities.items()})
        enc_channels = (self.encoder if stage == "early" else next(iter(self.encoders.values()))).channels
        if stage in ("fpn", "late"):
            self.fpns = nn.ModuleDict({m: self._fpn(enc_channels) for m in modalities})
        else:
            self.fpn = self._fpn(enc_channels)
        if stage == "late":
            assert fusion is not None  # checked above
            self.heads = nn.ModuleDict({m: head(in_channels=fpn_channels, num_levels=NUM_LEVELS) for m in modalities})
            self.late_keys = list(self.out_channels)
            self.fuse = nn.ModuleList(
                nn.ModuleList(fusion(channels=c, num_inputs=n) for c in (v if isinstance(v, (list, tuple)) else [v]))
                for v in self.out_channels.values()
            )
        else:
            self.head = head(in_channels=fpn_channels, num_levels=NUM_LEVELS)
        if stage == "backbone":
            assert fusion is not None  # checked above
            self.fuse = nn.ModuleList(fusion(channels=c, num_inputs=n) for c in enc_channels[1:])
        elif stage == "fpn":
            assert fusion is not None  # checked above
            self.fuse = nn.ModuleList(fusion(channels=fpn_channels, num_inputs=n) for _ in range(NUM_LEVELS))

    def _resnet(self, in_channels: int, modality: str | None) -> ResNet:
        opts = dict(self.backbone_options)
        if isinstance(opts.get("weights"), Mapping):
            opts["weights"] = dict(opts["weights"]).get(modality)
        return ResNet(
            depth=int(opts.get("depth", 18)),
            width=float(opts.get("width", 1.0)),
            in_channels=in_channels,
            weights=opts.get("weights"),
        )

    def _fpn(self, enc_channels: list[int]) -> FPN:
        return FPN(enc_channels[1:], self.fpn_channels, num_downsample=NUM_LEVELS - 3)

    @property
    def out_channels(self) -> dict:
        """The head's ``out_channels``: the keys and channels of ``forward``'s output."""
        return (next(iter(self.heads.values())) if self.stage == "late" else self.head).out_channels

    def forward(self, inputs: dict[str, Tensor], features: dict | None = None) -> dict[str, Tensor | list[Tensor]]:
        """The head's outputs for ``inputs``. ``features``: :meth:`frozen_features` of these inputs, computed
        before (a cache of them, :class:`ablate.jobs.experts.FeatureCache`); the per-modality parts are then not run."""
        if features is None:
            x = self._inputs(inputs)
            if self.stage == "early":
                return self.head(self.fpn(self.encoder(torch.cat(list(x.values()), 1))[1:]))
            features = {m: self._branch(m, t) for m, t in x.items()}
        if self.stage == "single":
            return self.head(self.fpn(features[self.single]))
        mods = list(self.modalities)
        if self.stage == "backbone":
            return self.head(self.fpn([op([features[m][k] for m in mods]) for k, op in enumerate(self.fuse)]))
        if self.stage == "fpn":
            return self.head([op([features[m][k] for m in mods]) for k, op in enumerate(self.fuse)])
        return {
            key: self._fuse_late(key, ops, [features[m][key] for m in mods])
            for key, ops in zip(self.late_keys, self.fuse)
        }

    def _inputs(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        missing = [m for m in self.modalities if m not in inputs]
        if missing:
            raise KeyError(f"fusion model needs inputs {list(self.modalities)}; missing {missing}, got {list(inputs)}")
        x = {m: inputs[m] for m in self.modalities}
        sizes = {m: tuple(t.shape[-2:]) for m, t in x.items()}
        if len(set(sizes.values())) > 1:
            raise ValueError(f"stage {self.stage!r} needs every modality at one H, W; got {sizes}")
        return x

    def _branch_parts(self, modality: str) -> list[nn.Module]:
        """The parts of ``modality`` before the fusion point, in order: encoder, then FPN (fpn, late), head (late)."""
        return [
            self.encoders[modality],
            *([self.fpns[modality]] if self.stage in ("fpn", "late") else []),
            *([self.heads[modality]] if self.stage == "late" else []),
        ]

    def _branch(self, modality: str, x: Tensor) -> list[Tensor] | dict:
        """``modality``'s features at the fusion point: C3..C5 (backbone, single), P3..P7 (fpn), head outputs (late)."""
        out = self.encoders[modality](x)[1:]
        for part in self._branch_parts(modality)[1:]:
            out = part(out)
        return out

    @property
    def cacheable(self) -> bool:
        """Whether every modality's parts before the fusion point are frozen experts (:meth:`load_expert` with
        ``freeze``), so that :meth:`frozen_features` of an input is a constant (SMoE §4.3)."""
        frozen = {id(part) for part in self._frozen}
        return self.stage in ("backbone", "fpn", "late") and all(
            id(part) in frozen for m in self.modalities for part in self._branch_parts(m)
        )

    @torch.no_grad()
    def frozen_features(self, inputs: dict[str, Tensor]) -> dict[str, list[Tensor] | dict]:
        """Per modality, the output of its frozen expert at the fusion point: C3..C5 (stage backbone), P3..P7
        (fpn), the expert head's output dict (late). ``forward(inputs, features=frozen_features(inputs))`` equals
        ``forward(inputs)``. Only for a :attr:`cacheable` model (else gradients would be lost)."""
        if not self.cacheable:
            raise ValueError(
                f"frozen_features needs every per-modality part frozen (load_expert(freeze=True)) at "
                f"stage backbone, fpn or late; this model is stage {self.stage!r} with "
                f"{len(self._frozen)} frozen part(s)"
            )
        return {m: self._branch(m, t) for m, t in self._inputs(inputs).items()}

    def _fuse_late(self, key: str, ops: nn.ModuleList, maps: list) -> Tensor | list[Tensor]:
        if isinstance(maps[0], (list, tuple)):
            if len(maps[0]) != len(ops):
                raise ValueError(f"head output {key!r} has {len(maps[0])} maps, its out_channels lists {len(ops)}")
            return [op([mp[k] for mp in maps]) for k, op in enumerate(ops)]
        return ops[0](maps)

    def num_parameters(self) -> int:
        """Number of parameters (trainable or not)."""
        return sum(p.numel() for p in self.parameters())

    def macs(self, input_shapes: dict[str, tuple[int, ...]]) -> int:
        """Multiply-accumulates of one forward pass on zero inputs of ``input_shapes`` ((B,)C,H,W; B = 1 if left out).

        Counted by ``torch.utils.flop_counter.FlopCounterMode`` (convolutions and matrix products; elementwise
        ops such as BatchNorm, ReLU, sum, max or sharpen count zero), MACs = FLOPs / 2. Run in eval mode.
        """
        device = next(self.parameters()).device
        inputs = {m: torch.zeros(s if len(s) == 4 else (1, *s), device=device) for m, s in input_shapes.items()}
        was_training = self.training
        self.eval()
        try:
            with torch.no_grad(), FlopCounterMode(display=False) as counter:
                self(inputs)
        finally:
            self.train(was_training)
        return counter.get_total_flops() // 2

    def fusion_modules(self) -> list[FusionOp]:
        """The fusion operators in forward order (C3..C5, P3..P7, or one per late output map); [] for early/single."""
        return [m for m in self.modules() if isinstance(m, FusionOp)]

    def load_expert(self, modality: str, expert: FusionModel, freeze: bool = True) -> None:
        """Copy a trained single-modality model into this model's parts for ``modality`` (SMoE §4.3 stage one).

        Copies the encoder, and the FPN (stages fpn, late) and head (late). ``freeze`` fixes their weights
        (requires_grad False) and keeps their BatchNorm statistics fixed (eval mode even under ``train()``).
        """
        if modality not in self.encoders:
            raise KeyError(
                f"no per-modality encoder for {modality!r} at stage {self.stage!r}; have {list(self.encoders)}"
            )
        if expert.stage != "single" or expert.single != modality:
            raise ValueError(
                f"expert for {modality!r} must be a stage 'single' model of that modality, "
                f"got stage {expert.stage!r} of {expert.single!r}"
            )
        for mine, theirs in zip(self._branch_parts(modality), (expert.encoders[modality], expert.fpn, expert.head)):
            mine.load_state_dict(theirs.state_dict())
            if freeze:
                self.freeze(mine)
