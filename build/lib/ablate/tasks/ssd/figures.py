"""Figures of the detection task: boxes over the camera image (ground truth beside predictions)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from ablate.metrics.kitti import LABEL_NAMES  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def _rgb(image: torch.Tensor) -> torch.Tensor:
    """[C, H, W] in 0-1 -> [H, W, 3] for imshow (one channel shown as grey)."""
    img = image.detach().float().cpu().clamp(0, 1).permute(1, 2, 0)
    return img.expand(-1, -1, 3) if img.shape[-1] == 1 else img[..., :3]


def _boxes(ax: Axes, boxes: torch.Tensor, captions: list[str], colours: list[str], dashed: list[bool]) -> None:
    for (x1, y1, x2, y2), caption, colour, dash in zip(boxes.tolist(), captions, colours, dashed):
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, lw=0.8, color=colour, ls="--" if dash else "-"))
        if caption:
            ax.text(
                x1,
                y1,
                caption,
                fontsize=5,
                color="white",
                va="bottom",
                bbox={"facecolor": colour, "alpha": 0.7, "pad": 0.5, "lw": 0},
            )


def draw_detections(
    images: torch.Tensor,
    targets: list[dict],
    preds: list[dict],
    conditions: list[str] | None,
    num_classes: int,
    score: float = 0.5,
) -> Figure:
    """Rows: frames; columns: ground truth (classes solid, KITTI's ignored Van / Person_sitting / DontCare
    dashed grey) and predictions with score >= ``score`` (class and score captioned)."""
    n = images.shape[0]
    h, w = images.shape[-2:]
    fig, axes = plt.subplots(n, 2, figsize=(6.4, n * (3.2 * h / w + 0.35) + 0.2), squeeze=False)
    palette = plt.get_cmap("tab10")
    colour = lambda c: palette(c % 10)  # noqa: E731
    for i in range(n):
        img = _rgb(images[i]).numpy()
        gt, p = targets[i], preds[i]
        labels = gt["labels"].tolist()
        ignored = [c >= num_classes for c in labels]
        axes[i, 0].imshow(img)
        _boxes(
            axes[i, 0],
            gt["boxes"].cpu().reshape(-1, 4),
            [LABEL_NAMES[c] if not x else "" for c, x in zip(labels, ignored)],
            ["grey" if x else colour(c) for c, x in zip(labels, ignored)],
            ignored,
        )
        keep = p["scores"] >= score
        axes[i, 1].imshow(img)
        _boxes(
            axes[i, 1],
            p["boxes"][keep].cpu(),
            [f"{LABEL_NAMES[c]} {s:.2f}" for c, s in zip(p["labels"][keep].tolist(), p["scores"][keep].tolist())],
            [colour(c) for c in p["labels"][keep].tolist()],
            [False] * int(keep.sum()),
        )
        where = f" ({conditions[i]})" if conditions else ""
        axes[i, 0].set_title(f"ground truth{where}", fontsize=8)
        axes[i, 1].set_title(f"prediction, score >= {score:g}", fontsize=8)
        for ax in axes[i]:
            ax.set_axis_off()
    fig.tight_layout()
    return fig
