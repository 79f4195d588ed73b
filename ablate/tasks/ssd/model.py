"""The DGFN network (Kim et al., seed 002 §III-A, Fig. 1): one VGG-16 SSD trunk per sensor, a fusion operator at
each of the six SSD maps, SSD's predictors on the fused maps."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import cast

import torch.nn.functional as F
from torch import Tensor, nn

from ablate.fusion.ops import FusionOp
from ablate.nn.vgg import VGG16SSD


class DGFN(nn.Module):
    """``forward(inputs: dict[str, Tensor[B, C, H, W]]) -> head outputs`` on the fused conv4_3, conv7, conv8_2,
    conv9_2, conv10_2 and conv11_2 maps (DGFN §III-A: "we collect the feature maps at the layers of conv4_3, conv7
    (FC7), conv8_2, conv9_2, conv10_2, and conv11_2 layers and combine them through the GFU").

    ``modalities``: {name: channels} in the operators' input order (camera first: GFU eq. 5's concatenation order
    only permutes conv weights). ``fusion``: called as ``fusion(channels=C_l, num_inputs=N)`` once per map
    (``fusion=gfu``: eq. 5-9; ``gated=False`` is the baseline "without GFU"). ``single``: one modality and no
    fusion, SSD on that sensor alone (Table II's "SSD* Mono" and "SSD* Lidar"). ``head``: called as
    ``head(in_channels=[C_1..C_6], num_levels=6)`` (:class:`ablate.tasks.ssd.head.SSDHead`). ``width`` scales the
    VGG channels; ``weights``: a local VGG-16 state dict for every trunk, or a dict modality -> file (§IV-A uses an
    ImageNet-trained VGG-16 for both).

    Trunks start from He et al.'s initialisation (normal, fan-out, as torchvision initialises VGG), then load
    ``weights`` where given: PyTorch's default initialisation shrinks the signal through the 13 convolutions of a
    VGG trunk without normalisation so far that an untrained DGFN's output hardly depends on its input.

    ``l2norm_scale``: the initial scale of each trunk's conv4_3 L2 normalisation (SSD's is 20, chosen for its
    predictor on ImageNet-trained conv4_3 features). Reading: DGFN does not say how conv4_3 is normalised before
    its GFU. Fed maps of norm 20, the conv4_3 GFU's weight maps (eq. 6-7, a 3x3 conv over 2K channels) saturate
    at 0 within a few Adam updates from scratch and stay shut (measured on the generated smoke-scale data, Adam at
    0.001: the conv4_3 gate means fall from 0.15 to 0.01 in 3 updates; started at scale 1 they stay at 0.4-0.5
    over 15 updates), so the DGFN rows start it at 1 (conf/model/dgfn.yaml) and the single-sensor SSD rows, with
    the predictor right after, at SSD's 20.

    ``batch_norm``: trunks with a BatchNorm after every conv (ScratchDet's remedy for SSD from scratch; see
    :mod:`ablate.nn.vgg`), not in DGFN. ``blank_running_stats``: in training, a trunk whose batch is one value
    throughout (a blanked sensor, DGFN §IV-A's corruption drawn for the whole update) normalises with its
    BatchNorms' running statistics and leaves them as they are, as at test. Such a batch has no statistics: its
    batch variance is 0, so BatchNorm divides by sqrt(eps) and the trunk's gradient norm reaches 10^2-10^3, and
    the running variance falls 10 % per such update (docs/recipes.md#detection_cpu).

    ``input_size``: the (H, W) every input is resized to (bilinear, antialiased) before the trunks, as SSD300
    warps its input to 300x300; null keeps the data's size (it must then be about 270 px or more on each side, for
    the unpadded conv10_2 / conv11_2). Reading: DGFN does not give its input size; SSD300's is taken. Boxes stay in
    the data's pixels: the default boxes are defined relative to the image (SSD eq. 4), so they follow the warp.
    """

    def __init__(
        self,
        modalities: Mapping[str, int],
        head: Callable[..., nn.Module],
        fusion: Callable[..., nn.Module] | None = None,
        single: str | None = None,
        width: float = 1.0,
        input_size: tuple[int, int] | None = (300, 300),
        weights: str | Mapping | None = None,
        l2norm_scale: float = 20.0,
        batch_norm: bool = False,
        blank_running_stats: bool = False,
    ) -> None:
        super().__init__()
        modalities = {str(k): int(v) for k, v in dict(modalities).items()}
        if single is not None:
            if single not in modalities:
                raise ValueError(f"model.single: {single!r} is not one of the modalities {list(modalities)}")
            modalities = {single: modalities[single]}
        elif len(modalities) < 2:
            raise ValueError(f"DGFN fuses >= 2 modalities, got {list(modalities)}; set model.single for one")
        elif fusion is None:
            raise ValueError("DGFN needs a fusion operator (`fusion`, e.g. fusion=gfu) unless model.single is set")
        if input_size is not None and (len(input_size) != 2 or min(input_size) < 1):
            raise ValueError(f"model.input_size: expected [H, W], got {input_size}")
        self.modalities, self.single = modalities, single
        self.blank_running_stats = bool(blank_running_stats)
        self.input_size = tuple(int(s) for s in input_size) if input_size is not None else None
        files = weights if isinstance(weights, Mapping) else {m: weights for m in modalities}
        self.branches = nn.ModuleDict({m: VGG16SSD(c, width, batch_norm=batch_norm) for m, c in modalities.items()})
        for m, branch in self.branches.items():
            he_init(branch)
            nn.init.constant_(branch.l2norm.weight, float(l2norm_scale))
            if files.get(m) is not None:
                branch.load(files[m])
        channels = next(iter(self.branches.values())).channels
        self.fuse = (
            # without single, fusion is not None (checked above)
            nn.ModuleList(
                cast("Callable[..., nn.Module]", fusion)(channels=c, num_inputs=len(modalities)) for c in channels
            )
            if single is None
            else nn.ModuleList()
        )
        self.head = head(in_channels=channels, num_levels=len(channels))

    @property
    def out_channels(self) -> dict:
        return self.head.out_channels

    def forward(self, inputs: dict[str, Tensor]) -> dict:
        missing = [m for m in self.modalities if m not in inputs]
        if missing:
            raise KeyError(f"DGFN needs inputs {list(self.modalities)}; missing {missing}, got {list(inputs)}")
        maps = {m: self._trunk(m, self._resize(inputs[m])) for m in self.modalities}
        if self.single is not None:
            return self.head(maps[self.single])
        return self.head([op([maps[m][k] for m in self.modalities]) for k, op in enumerate(self.fuse)])

    def _trunk(self, modality: str, x: Tensor) -> Tensor:
        branch = self.branches[modality]
        if not (self.training and self.blank_running_stats and bool(x.amax() == x.amin())):
            return branch(x)
        norms = [m for m in branch.modules() if isinstance(m, nn.BatchNorm2d) and m.training]
        for m in norms:
            m.eval()
        try:
            return branch(x)
        finally:
            for m in norms:
                m.train()

    def _resize(self, x: Tensor) -> Tensor:
        if self.input_size is None or tuple(x.shape[-2:]) == self.input_size:
            return x
        return F.interpolate(x, size=self.input_size, mode="bilinear", align_corners=False, antialias=True)

    def fusion_modules(self) -> list[FusionOp]:
        """The fusion operators, conv4_3 first; [] for a single sensor."""
        return [m for m in self.modules() if isinstance(m, FusionOp)]


def he_init(module: nn.Module) -> None:
    """He et al. (2015) normal initialisation, fan-out, of every convolution; biases zero."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            nn.init.zeros_(m.bias)
