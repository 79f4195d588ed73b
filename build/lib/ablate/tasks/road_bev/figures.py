"""Figures of the road task: predicted road beside the ground truth in camera space and in BEV (BiFNet Fig. 5), and
CBF's gains per channel (eq. 10) at each fusion point."""

from __future__ import annotations

from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from torch import nn


def _image(batch: dict, i: int) -> np.ndarray | None:
    for key in ("rgb", "intensity"):
        if key in batch:
            img = batch[key][i].permute(1, 2, 0).float().clamp(0, 1)
            return (img.expand(-1, -1, 3) if img.shape[-1] == 1 else img).numpy()
    return None


def draw_roads(batch: dict, probs: dict[str, torch.Tensor]) -> Figure:
    """One row per frame: image, then per space the ground truth and the predicted road probability (BEV rasters
    drawn with the far end up and left on the left, as the driver sees them)."""
    columns: list[tuple[str, tuple[str, str] | None]] = [("image", None)]
    if "cam" in probs or "free_space" in batch:
        columns += [("camera ground truth", ("gt", "free_space")), ("camera prediction", ("p", "cam"))]
    if "bev" in probs or "road_bev" in batch:
        columns += [("BEV ground truth", ("gt", "road_bev")), ("BEV prediction", ("p", "bev"))]
    n = len(next(iter(probs.values()))) if probs else 1
    widths = [3 if kind is None or "BEV" not in title else 1 for title, kind in columns]
    fig, axes = plt.subplots(
        n,
        len(columns),
        figsize=(2.2 * sum(widths) / 1.5, 1.6 * n + 0.6),
        squeeze=False,
        gridspec_kw={"width_ratios": widths},
    )
    for i in range(n):
        for ax, (title, kind) in zip(axes[i], columns):
            ax.set_axis_off()
            if i == 0:
                ax.set_title(title, fontsize=8)
            if kind is None:
                img = _image(batch, i)
                if img is not None:
                    ax.imshow(img)
                continue
            src, key = kind
            data = batch.get(key) if src == "gt" else probs.get(key)
            if data is None:
                continue
            ax.imshow(
                data[i].reshape(data.shape[-2:]).float().numpy(), vmin=0, vmax=1, cmap="magma", interpolation="nearest"
            )
    fig.tight_layout()
    return fig


def draw_gains(operators: list[nn.Module], levels: tuple[int, ...]) -> Figure | None:
    """Bars of the mean gain per channel of the camera and the LiDAR input, one panel per operator with gains
    (camera group and BEV group per level); None when no operator keeps gains (plain sum, LidCamNet, PLARD)."""
    from ablate.fusion.bidirectional import gains

    panels = []
    groups = ("camera group", "BEV group") if len(operators) == 2 * len(levels) else ("",)
    for k, op in enumerate(operators):
        q = gains(op)
        if q is None or any(g.ndim != 4 or g.shape[-2:] != (1, 1) for g in q):
            continue
        level = levels[k // len(groups)] if levels else k
        panels.append((f"C{level + 2} {groups[k % len(groups)]}".strip(), [g.mean(0).flatten().cpu() for g in q]))
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 1.4 * len(panels) + 0.6), squeeze=False)
    for ax, (title, q) in zip(axes[:, 0], panels):
        x = np.arange(len(q[0]))
        for j, (g, name) in enumerate(zip(q, ("camera", "LiDAR"))):
            ax.bar(x + (j - 0.5) * 0.4, g.numpy(), 0.4, label=name)
        ax.set_ylim(0, 1)
        ax.set_title(title, fontsize=8)
        ax.set_ylabel("gain", fontsize=7)
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("channel")
    fig.tight_layout()
    return fig
