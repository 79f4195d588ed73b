"""Figures of the instance task: masks over the image (SMoE Fig. 6) and gate maps over the inputs (DGFN Fig. 5)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from ablate.tasks.yolact import CLASSES  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def _rgb(image: torch.Tensor) -> torch.Tensor:
    """[C, H, W] in 0-1 -> [H, W, 3] for imshow (one channel shown as grey)."""
    img = image.detach().float().cpu().clamp(0, 1).permute(1, 2, 0)
    return img.expand(-1, -1, 3) if img.shape[-1] == 1 else img[..., :3]


def _size(rows: int, cols: int, hw: tuple[int, int], panel: float = 3.2) -> tuple[float, float]:
    """Figure size for panels ``panel`` inches wide keeping the images' aspect, with room for titles."""
    return panel * cols, rows * (panel * hw[0] / hw[1] + 0.35) + 0.2


def _overlay(ax: Axes, image: torch.Tensor, masks: torch.Tensor, boxes: torch.Tensor, captions: list[str]) -> None:
    """Each mask in its own colour at half opacity over ``image`` [H, W, 3], with its box and caption."""
    shown = image.clone()
    colours = plt.get_cmap("tab10")
    for k, mask in enumerate(masks.bool()):
        colour = torch.tensor(colours(k % 10)[:3], dtype=shown.dtype)
        shown[mask] = 0.5 * shown[mask] + 0.5 * colour
    ax.imshow(shown.numpy())
    for k, (box, caption) in enumerate(zip(boxes.tolist(), captions)):
        x1, y1, x2, y2 = box
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, lw=0.8, color=colours(k % 10)))
        ax.text(
            x1,
            y1,
            caption,
            fontsize=6,
            color="white",
            va="bottom",
            bbox={"facecolor": colours(k % 10), "alpha": 0.7, "pad": 0.5, "lw": 0},
        )
    ax.set_axis_off()


def draw_instances(
    images: torch.Tensor, targets: list[dict], preds: list[dict], conditions: list[str] | None, score: float = 0.5
) -> Figure:
    """Rows: frames; columns: ground truth, predictions with score >= ``score`` (class and score captioned)."""
    n = images.shape[0]
    fig, axes = plt.subplots(n, 2, figsize=_size(n, 2, images.shape[-2:]), squeeze=False)
    for i in range(n):
        img = _rgb(images[i])
        gt = targets[i]
        _overlay(
            axes[i, 0],
            img,
            gt["masks"].cpu(),
            gt["boxes"].cpu().reshape(-1, 4),
            [CLASSES[c] if c < len(CLASSES) else str(c) for c in gt["labels"].tolist()],
        )
        keep = preds[i]["scores"] >= score
        p = {k: v[keep] for k, v in preds[i].items()}
        _overlay(
            axes[i, 1],
            img,
            p["masks"],
            p["boxes"],
            [
                f"{CLASSES[c] if c < len(CLASSES) else c} {s:.2f}"
                for c, s in zip(p["labels"].tolist(), p["scores"].tolist())
            ],
        )
        where = f" ({conditions[i]})" if conditions else ""
        axes[i, 0].set_title(f"ground truth{where}", fontsize=8)
        axes[i, 1].set_title(f"prediction, score >= {score:g}", fontsize=8)
    fig.tight_layout()
    return fig


def draw_gates(images: dict[str, torch.Tensor], gates: list[torch.Tensor], conditions: list[str] | None) -> Figure:
    """Rows: frames; per modality its input, then its gate map (``gates[k]`` [B, h, w] in 0-1, bilinearly
    upsampled to the input size) over that input."""
    names = list(images)
    if len(gates) != len(names):
        raise ValueError(f"draw_gates: {len(gates)} gate maps for modalities {names}")
    first = next(iter(images.values()))
    n = first.shape[0]
    width, height = _size(n, 2 * len(names), first.shape[-2:])
    fig, axes = plt.subplots(n, 2 * len(names), figsize=(width + 1.2, height), squeeze=False)
    for k, (name, gate) in enumerate(zip(names, gates)):
        size = images[name].shape[-2:]
        up = F.interpolate(gate[:, None].float(), size=size, mode="bilinear", align_corners=False)[:, 0]
        for i in range(n):
            img = _rgb(images[name][i])
            axes[i, 2 * k].imshow(img.numpy())
            axes[i, 2 * k + 1].imshow(img.mean(-1).numpy(), cmap="gray")
            heat = axes[i, 2 * k + 1].imshow(up[i].numpy(), cmap="jet", vmin=0, vmax=1, alpha=0.6)
            where = f" ({conditions[i]})" if conditions else ""
            axes[i, 2 * k].set_title(f"{name}{where}", fontsize=8)
            axes[i, 2 * k + 1].set_title(f"gate of {name}, mean {up[i].mean():.2f}", fontsize=8)
            for ax in axes[i, 2 * k : 2 * k + 2]:
                ax.set_axis_off()
    fig.colorbar(heat, ax=axes.ravel().tolist(), shrink=0.6, label="gate weight")
    return fig


def draw_rows(
    images: torch.Tensor, targets: list[dict], preds: dict[str, list[dict]], captions: list[str], score: float = 0.5
) -> Figure:
    """SMoE Fig. 6: rows are frames, columns the ground truth and then each method's masks (score >= ``score``)
    on the same frames; ``preds[name][i]`` is method ``name``'s prediction on frame ``i``."""
    n, names = images.shape[0], list(preds)
    fig, axes = plt.subplots(
        n, 1 + len(names), figsize=_size(n, 1 + len(names), images.shape[-2:], panel=2.6), squeeze=False
    )
    for i in range(n):
        img = _rgb(images[i])
        gt = targets[i]
        _overlay(axes[i, 0], img, gt["masks"].cpu(), gt["boxes"].cpu().reshape(-1, 4), [""] * len(gt["labels"]))
        axes[i, 0].set_title(f"ground truth ({captions[i]})", fontsize=7)
        for j, name in enumerate(names, start=1):
            p = preds[name][i]
            keep = p["scores"] >= score
            _overlay(axes[i, j], img, p["masks"][keep].cpu(), p["boxes"][keep].cpu(), [""] * int(keep.sum()))
            axes[i, j].set_title(name, fontsize=7)
    fig.tight_layout()
    return fig
