"""The ChiNet and its variants (John et al., "Sensor Fusion of Intensity and Depth Cues using the ChiNet").

ChiNet §III-A and Fig. 2: two input branches (intensity, depth), each an encoder of 3x3 'same' conv layers with
ReLU and 2x2 max-pooling; two output branches (free space, road objects), each a decoder of 2x2 upsampling and
conv layers. Every decoder level receives the encoder features of that level from *every* input branch, and
these are fused with the upsampled decoder features by concatenation. Each output branch ends in a sigmoid
(binary cross-entropy); dropout 0.2 (Fig. 3).

Table I gives the variants:

| variant | input branches | output branches | skip connections |
|---|---|---|---|
| chinet | intensity; depth | free space; road objects | both encoders -> both decoders |
| simo   | intensity + depth as one 2-channel input | free space; road objects | encoder -> both decoders |
| miso   | intensity; depth | one 3-class softmax | both encoders -> the decoder |
| iimo   | intensity only | free space; road objects | encoder -> both decoders |
| unet   | intensity + depth as one 2-channel input | one 3-class softmax | encoder -> decoder |
| fusenet | intensity; depth, depth summed into the intensity branch after every encoder level | one 3-class softmax | between the encoders only |

Fig. 3's layer table did not survive in the text, so the filter numbers are the config's ``widths`` (doubling per
level, as in U-Net); the bottleneck is the deepest encoder level. The FuseNet reading follows Table I ("skip
connection between intensity encoder layers and depth encoder layers") and the issue's "depth summed into the RGB
encoder": its decoder gets no encoder skips.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ablate.nn.unet import ConvBlock, DecoderBlock, Encoder

MULTILABEL = ("free_space", "road_objects")
VARIANTS = ("chinet", "simo", "miso", "iimo", "unet", "fusenet")


class Decoder(nn.Module):
    """One output branch: from the bottleneck up through every encoder level, with skips, to ``out_ch`` logits."""

    def __init__(
        self, bottleneck: int, skip_channels: list[int], widths: list[int], out_ch: int, dropout: float
    ) -> None:
        super().__init__()
        if len(widths) < 2:
            raise ValueError(f"ChiNet needs at least two encoder levels (widths), got {widths}")
        ins = [bottleneck] + widths[-2:0:-1]
        self.blocks = nn.ModuleList(
            DecoderBlock(c, s, w, dropout) for c, s, w in zip(ins, skip_channels[-2::-1], widths[-2::-1])
        )
        self.out = nn.Conv2d(widths[0], out_ch, 1)

    def forward(self, x: Tensor, skips: list[Tensor]) -> Tensor:
        for block, skip in zip(self.blocks, skips[-2::-1]):
            x = block(x, skip)
        return self.out(x)


class ChiNet(nn.Module):
    """Encoders over groups of modalities, decoders for free space + road objects (multilabel) or 3 classes."""

    def __init__(
        self,
        branches: list[list[str]],
        channels: dict[str, int],
        widths: list[int],
        multilabel: bool,
        dropout: float = 0.2,
    ) -> None:
        super().__init__()
        self.branches = branches
        self.encoders = nn.ModuleList(Encoder(sum(channels[m] for m in b), widths, dropout) for b in branches)
        n = len(branches)
        skip_channels = [n * w for w in widths]
        outputs = {name: 1 for name in MULTILABEL} if multilabel else {"semantic": 3}
        self.decoders = nn.ModuleDict(
            {name: Decoder(skip_channels[-1], skip_channels, widths, c, dropout) for name, c in outputs.items()}
        )

    def forward(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        feats = [enc(torch.cat([inputs[m] for m in b], 1)) for enc, b in zip(self.encoders, self.branches)]
        skips = [torch.cat(level, 1) for level in zip(*feats)]
        return {name: dec(skips[-1], skips) for name, dec in self.decoders.items()}


class FuseNet(nn.Module):
    """FuseNet as ChiNet Table I describes it: depth features summed into the intensity encoder after every
    level (Hazirbas et al.), one multiclass decoder without encoder skips."""

    def __init__(
        self, intensity: str, depth: str, channels: dict[str, int], widths: list[int], dropout: float = 0.2
    ) -> None:
        super().__init__()
        self.intensity, self.depth = intensity, depth
        ins = widths[:-1]
        self.rgb = nn.ModuleList(ConvBlock(c, w, dropout) for c, w in zip([channels[intensity]] + ins, widths))
        self.dep = nn.ModuleList(ConvBlock(c, w, dropout) for c, w in zip([channels[depth]] + ins, widths))
        self.pool = nn.MaxPool2d(2)
        self.up = nn.ModuleList(ConvBlock(c, w, dropout) for c, w in zip(widths[:0:-1], widths[-2::-1]))
        self.out = nn.Conv2d(widths[0], 3, 1)

    def forward(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        x, d = inputs[self.intensity], inputs[self.depth]
        sizes = []
        for i, (rgb, dep) in enumerate(zip(self.rgb, self.dep)):
            if i:
                x, d = self.pool(x), self.pool(d)
            d = dep(d)
            x = rgb(x) + d
            sizes.append(x.shape[-2:])
        for block, size in zip(self.up, sizes[-2::-1]):
            x = block(nn.functional.interpolate(x, size=size, mode="nearest"))
        return {"semantic": self.out(x)}


def build(variant: str, modalities: dict[str, int], widths: list[int], dropout: float = 0.2) -> nn.Module:
    """A ChiNet-family model. ``modalities`` names the intensity input first and the depth input second."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown ChiNet variant {variant!r}; valid: {', '.join(VARIANTS)}")
    names = list(modalities)
    if len(names) < (1 if variant == "iimo" else 2):
        raise ValueError(f"ChiNet variant {variant!r} needs an intensity and a depth modality, got {names}")
    widths = list(widths)
    channels = dict(modalities)
    intensity, depth = names[0], names[-1]
    if variant == "fusenet":
        return FuseNet(intensity, depth, channels, widths, dropout)
    branches = {
        "chinet": [[intensity], [depth]],
        "simo": [[intensity, depth]],
        "miso": [[intensity], [depth]],
        "iimo": [[intensity]],
        "unet": [[intensity, depth]],
    }[variant]
    return ChiNet(branches, channels, widths, multilabel=variant in ("chinet", "simo", "iimo"), dropout=dropout)
