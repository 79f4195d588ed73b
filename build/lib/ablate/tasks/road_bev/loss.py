"""BiFNet's loss (Li et al., seed 004 §IV-C, eq. 13): per-pixel focal loss (Lin et al. [30]) in camera space plus
lambda times the focal loss in BEV space.

Values the paper leaves out, chosen here (``task.loss`` in the config):

* ``gamma`` = 2 and ``alpha`` = 0.25: the pair Lin et al. [30] recommend and BiFNet cites without numbers. ``alpha``
  weighs the road pixels, 1 - ``alpha`` the background. MaxF and AP take the best of 256 thresholds, so ``alpha``
  moves the operating point more than the ranking the metrics score.
* ``lam`` (lambda) = 1: "the loss of camera space can make the network see objects farther away, while the loss of
  BEV can make the distant and near objects distribute equally": neither space is preferred. N in eq. 13, "the
  number of the pixels in one batch", is read per space: each term is the mean over its own valid pixels, so
  lambda = 1 weighs the two spaces equally although the image has ~17x the BEV's cells.

Valid pixels: camera pixels whose ground truth is not void (``road_valid``; KITTI's black), BEV cells whose centre
sees a valid image pixel (``road_bev_valid``). Logits below the target's resolution are upsampled bilinearly first.
A model without a BEV output (image only, camera-space fusion) has the camera term only, and a BEV-only model the
BEV term only.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def upsample(logits: Tensor, size: tuple[int, int]) -> Tensor:
    return (
        logits
        if logits.shape[-2:] == tuple(size)
        else F.interpolate(logits, size=size, mode="bilinear", align_corners=False)
    )


def focal_loss(
    logits: Tensor, target: Tensor, valid: Tensor | None = None, alpha: float = 0.25, gamma: float = 2.0
) -> Tensor:
    """Mean over ``valid`` pixels of -alpha_t (1 - p_t)^gamma log(p_t) (Lin et al. [30]); 0 with no valid pixel."""
    target = target.to(logits.dtype)
    ce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    p = torch.sigmoid(logits)
    p_t = p * target + (1 - p) * (1 - target)
    alpha_t = alpha * target + (1 - alpha) * (1 - target)
    loss = alpha_t * (1 - p_t).pow(gamma) * ce
    if valid is None:
        return loss.mean()
    valid = valid.to(loss.dtype)
    return (loss * valid).sum() / valid.sum().clamp(min=1.0)


class RoadLoss(nn.Module):
    """``forward(outputs, batch) -> {"loss", "loss_cam", "loss_bev"}``: eq. 13 over whichever of ``road_cam`` and
    ``road_bev`` the model returns (targets ``free_space`` / ``road_valid`` and ``road_bev`` / ``road_bev_valid``)."""

    def __init__(self, alpha: float = 0.25, gamma: float = 2.0, lam: float = 1.0) -> None:
        super().__init__()
        if not 0.0 <= alpha <= 1.0 or gamma < 0 or lam < 0:
            raise ValueError(
                f"task.loss: need 0 <= alpha <= 1, gamma >= 0, lam >= 0; got alpha={alpha}, gamma={gamma}, lam={lam}"
            )
        self.alpha, self.gamma, self.lam = float(alpha), float(gamma), float(lam)

    def forward(self, outputs: dict[str, Tensor], batch: dict) -> dict[str, Tensor]:
        if not {"road_cam", "road_bev"} & set(outputs):
            raise KeyError(f"road loss: the model returned neither road_cam nor road_bev, got {sorted(outputs)}")
        zero = next(iter(outputs.values())).new_zeros(())
        parts = {"loss_cam": zero, "loss_bev": zero}
        for key, target, valid, name in (
            ("road_cam", "free_space", "road_valid", "loss_cam"),
            ("road_bev", "road_bev", "road_bev_valid", "loss_bev"),
        ):
            if key in outputs:
                if target not in batch:
                    raise KeyError(f"road loss: output {key} needs batch[{target!r}] (list it in targets)")
                logits = upsample(outputs[key], batch[target].shape[-2:])
                parts[name] = focal_loss(logits, batch[target], batch.get(valid), self.alpha, self.gamma)
        return {"loss": parts["loss_cam"] + self.lam * parts["loss_bev"], **parts}

    def extra_repr(self) -> str:
        return f"alpha={self.alpha}, gamma={self.gamma}, lam={self.lam}"
