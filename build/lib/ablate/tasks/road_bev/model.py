"""BiFNet's network (Li et al., seed 004 §IV-C, Fig. 4) and its single-modal and camera-space relatives.

Every modality has a branch: a ResNet (C2..C5, "five convolution blocks same as ResNet"), a top-down FPN over
C2..C5 and a road head (3x3 conv + ReLU, 1x1 conv) giving road logits at stride 4 in that modality's space. The
BEV raster (``bev``) lives in BEV space, every other modality in the camera's perspective.

``stage`` (the ``stage`` config group):

* ``single``: one branch; outputs ``road_cam`` or ``road_bev`` (the image-only and BEV-only rows, and the experts).
* ``backbone``: one branch per modality, fused after the backbones at each level of ``levels`` (0..3: C2..C5,
  "at different scales", §V-E); the fused features feed the branches' decoders.
  - a camera modality and ``bev``: one :class:`~ablate.fusion.bidirectional.BidirectionalFusion` per level (two
    groups, DST -> DT -> operator, through the space transform ``space``); outputs ``road_cam`` (the prediction,
    Fig. 4) and ``road_bev``.
  - two camera-space modalities (LidCamNet and PLARD, §V-F, fusing LiDAR projected into the image): the operator
    fuses them directly at each level into the first modality's branch; outputs ``road_cam``.

Two-stage training (BiFNet §V-B "the two networks are trained separately first"; :mod:`ablate.jobs.experts`):
:meth:`load_expert` copies a trained single-modal branch in (its encoder frozen with ``freeze``; its decoder and
head, which see the fused features afterwards, as a trainable start).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch import Tensor, nn

from ablate.fusion.bidirectional import BidirectionalFusion, fusion_op
from ablate.fusion.geometry import BevGrid, Geometry
from ablate.fusion.space import build_space
from ablate.nn.fpn import FPN
from ablate.nn.frozen import FreezableModel
from ablate.nn.resnet import ResNet

BEV_MODALITIES = ("bev",)
STAGES = ("single", "backbone")
OUTPUTS = {"cam": "road_cam", "bev": "road_bev"}


def space_of(modality: str) -> str:
    return "bev" if modality in BEV_MODALITIES else "cam"


class Branch(nn.Module):
    """ResNet -> FPN (C2..C5 -> P2..P5) -> road logits [B,1,H/4,W/4] from P2; ``decoder=False`` keeps the encoder
    only (a branch fused into another one)."""

    def __init__(self, in_channels: int, backbone: Mapping, fpn_channels: int, decoder: bool = True) -> None:
        super().__init__()
        self.encoder = ResNet(
            depth=int(backbone.get("depth", 18)),
            width=float(backbone.get("width", 1.0)),
            in_channels=in_channels,
            weights=backbone.get("weights"),
        )
        if decoder:
            self.decoder = FPN(self.encoder.channels, fpn_channels, num_downsample=0)
            self.head = nn.Sequential(
                nn.Conv2d(fpn_channels, fpn_channels, 3, padding=1),
                nn.ReLU(inplace=True),
                nn.Conv2d(fpn_channels, 1, 1),
            )

    def decode(self, features: list[Tensor]) -> Tensor:
        return self.head(self.decoder(features)[0])


class RoadNet(FreezableModel):
    """Road segmentation in camera and BEV space; ``forward(batch) -> {"road_cam"?: [B,1,H/4,W/4], "road_bev"?:
    [B,1,Hb/4,Wb/4]}`` (logits). The batch holds the modalities and, for a bidirectional model, the geometry of
    :class:`~ablate.fusion.geometry.Geometry` (``calib``, ``height_image``, ``height_bev``, ``lidar_points``).

    ``fusion``: builds an operator as ``fusion(channels=, num_inputs=)`` (a partial of ``ablate.fusion.build``);
    ``space``: a name of ``ablate.fusion.space.SPACES``; ``context``: CBF's gains in front of the operator ("+CBF",
    :class:`~ablate.fusion.bidirectional.WithContext`); ``grid``: the BEV raster (``data.bev``); ``backbone``:
    ResNet ``depth``, ``width``, ``weights``.
    """

    def __init__(
        self,
        stage: str,
        modalities: Mapping[str, int],
        fusion: Callable[..., nn.Module] | None = None,
        space: str = "dst",
        context: bool = False,
        backbone: Mapping | None = None,
        fpn_channels: int = 64,
        single: str | None = None,
        grid: Mapping | None = None,
        levels: tuple[int, ...] = (0, 1, 2, 3),
    ) -> None:
        super().__init__()
        if stage not in STAGES:
            raise ValueError(f"model road: unknown stage {stage!r}; valid: {', '.join(STAGES)}")
        modalities = {str(k): int(v) for k, v in dict(modalities).items()}
        if stage == "single":
            if single not in modalities:
                raise ValueError(
                    f"model road: stage 'single' needs stage.modality in {list(modalities)}, got {single!r}"
                )
            modalities = {single: modalities[single]}
        self.stage, self.single, self.modalities = stage, single if stage == "single" else None, modalities
        self.grid, self.levels = BevGrid.from_config(grid), tuple(int(k) for k in levels)
        self.mode = "single" if stage == "single" else self._mode(modalities)
        backbone = dict(backbone or {})
        first = next(iter(modalities))
        self.branches = nn.ModuleDict(
            {
                m: Branch(c, backbone, fpn_channels, decoder=self.mode != "perspective" or m == first)
                for m, c in modalities.items()
            }
        )
        if self.mode == "single":
            return
        if fusion is None:
            raise ValueError("model road: stage 'backbone' needs a fusion operator (`fusion`)")
        if any(k not in range(4) for k in self.levels) or not self.levels:
            raise ValueError(f"model road: levels must be indices 0..3 of C2..C5, got {list(self.levels)}")
        channels = {m: b.encoder.channels for m, b in self.branches.items()}
        if self.mode == "bidirectional":
            cam, bev = self.cam, self.bev
            self.fuse = nn.ModuleList(
                BidirectionalFusion(
                    channels[cam][k], channels[bev][k], build_space(space), 2 ** (k + 2), fusion, context
                )
                for k in self.levels
            )
        else:
            self.fuse = nn.ModuleList(fusion_op(fusion, channels[first][k], 2, context) for k in self.levels)
        self.space_name = space if self.mode == "bidirectional" else None

    @staticmethod
    def _mode(modalities: Mapping[str, int]) -> str:
        spaces = [space_of(m) for m in modalities]
        if len(modalities) == 2 and sorted(spaces) == ["bev", "cam"]:
            return "bidirectional"
        if len(modalities) == 2 and spaces == ["cam", "cam"]:
            return "perspective"
        raise ValueError(
            f"model road: stage 'backbone' fuses a camera-space modality with `bev`, or two camera-space "
            f"modalities; got {list(modalities)}"
        )

    @property
    def cam(self) -> str:
        return next(m for m in self.modalities if space_of(m) == "cam")

    @property
    def bev(self) -> str:
        return next(m for m in self.modalities if space_of(m) == "bev")

    def forward(self, inputs: dict[str, Tensor], features: dict | None = None) -> dict[str, Tensor]:
        missing = [m for m in self.modalities if m not in inputs and features is None]
        if missing:
            raise KeyError(f"model road needs inputs {list(self.modalities)}; missing {missing}, got {sorted(inputs)}")
        if features is None:
            features = {m: self.branches[m].encoder(inputs[m]) for m in self.modalities}
        if self.mode == "single":
            assert self.single is not None  # set with mode single
            return {OUTPUTS[space_of(self.single)]: self.branches[self.single].decode(features[self.single])}
        if self.mode == "perspective":
            first, second = self.modalities
            fused = list(features[first])
            for k, op in zip(self.levels, self.fuse):
                fused[k] = op([fused[k], features[second][k]])
            return {"road_cam": self.branches[first].decode(fused)}
        cam, bev = self.cam, self.bev
        geometry = Geometry.from_batch(inputs, self.grid, self._image_size(inputs, features))
        f_cam, f_bev = list(features[cam]), list(features[bev])
        for k, module in zip(self.levels, self.fuse):
            f_cam[k], f_bev[k] = module(f_cam[k], f_bev[k], geometry)
        return {"road_cam": self.branches[cam].decode(f_cam), "road_bev": self.branches[bev].decode(f_bev)}

    def _image_size(self, inputs: dict, features: dict) -> tuple[int, int]:
        if self.cam in inputs:
            return tuple(inputs[self.cam].shape[-2:])
        if "height_image" in inputs:
            return tuple(inputs["height_image"].shape[-2:])
        raise KeyError(f"model road: the image size needs batch[{self.cam!r}] or batch['height_image']")

    @property
    def cacheable(self) -> bool:
        """Whether every encoder is a frozen expert, so :meth:`frozen_features` of a frame is a constant."""
        frozen = {id(p) for p in self._frozen}
        return self.mode != "single" and all(id(b.encoder) in frozen for b in self.branches.values())

    @torch.no_grad()
    def frozen_features(self, inputs: dict[str, Tensor]) -> dict[str, list[Tensor]]:
        """C2..C5 of every frozen encoder: ``forward(inputs, features=frozen_features(inputs))`` equals
        ``forward(inputs)``."""
        if not self.cacheable:
            raise ValueError("frozen_features needs every encoder frozen (load_expert(freeze=True))")
        return {m: self.branches[m].encoder(inputs[m]) for m in self.modalities}

    def load_expert(self, modality: str, expert: RoadNet, freeze: bool = True) -> None:
        """Copy a trained single-modal model (stage ``single`` of ``modality``) into this model's branch: the encoder
        (frozen, BatchNorm statistics fixed, with ``freeze``), and the decoder and head where this branch has them."""
        if modality not in self.branches:
            raise KeyError(f"no branch for {modality!r}; have {list(self.branches)}")
        if getattr(expert, "stage", None) != "single" or expert.single != modality:
            raise ValueError(f"expert for {modality!r} must be a stage 'single' road model of that modality")
        mine, theirs = self.branches[modality], expert.branches[modality]
        mine.encoder.load_state_dict(theirs.encoder.state_dict())
        if hasattr(mine, "decoder"):
            mine.decoder.load_state_dict(theirs.decoder.state_dict())
            mine.head.load_state_dict(theirs.head.state_dict())
        if freeze:
            self.freeze(mine.encoder)

    def fusion_modules(self) -> list[nn.Module]:
        """The operators in forward order (per level: camera group, then BEV group); [] for a single branch."""
        if self.mode == "single":
            return []
        return [op for m in self.fuse for op in (m.operators() if isinstance(m, BidirectionalFusion) else [m])]
