"""SSD inference: default boxes + offsets -> boxes, per-class greedy NMS (SSD §3, "Inference time")."""

from __future__ import annotations

import torch
from torch import Tensor

from ablate.tasks.boxes import VARIANCES, Anchors, decode_boxes, flatten_levels, nms


@torch.no_grad()
def decode(
    outputs: dict,
    image_size: tuple[int, int],
    anchors: Anchors,
    score_thresh: float = 0.01,
    nms_iou: float = 0.45,
    top_k: int = 400,
    max_detections: int = 200,
    variances: tuple[float, float] = VARIANCES,
) -> list[dict[str, Tensor]]:
    """The head's maps -> one dict per image in :class:`~ablate.metrics.kitti.KittiAP`'s format: ``boxes`` (N, 4)
    xyxy pixels clipped to the image, ``scores`` (N,), ``labels`` (N,) in [0, K), highest score first.

    SSD §3: "Given the large number of boxes generated from our method, it is essential to perform non-maximum
    suppression (nms) efficiently during inference. By using a confidence threshold of 0.01, we can filter out
    most boxes. We then apply nms with jaccard overlap of 0.45 per class and keep the top 200 detections per
    image." Class scores are softmax probabilities; per class at most ``top_k`` boxes above ``score_thresh`` enter
    the greedy NMS (:func:`ablate.tasks.boxes.nms`; SSD's implementation: 400).
    """
    counts = anchors.num_per_level
    probs = flatten_levels(outputs["cls"], outputs["cls"][0].shape[1] // counts[0]).softmax(-1)[..., 1:]
    loc = flatten_levels(outputs["box"], 4)
    anchors_t = anchors(image_size, [tuple(m.shape[-2:]) for m in outputs["cls"]], loc.device)
    if anchors_t.shape[0] != loc.shape[1]:
        raise ValueError(f"decode: {loc.shape[1]} predicted boxes for {anchors_t.shape[0]} default boxes")
    h, w = image_size
    limits = torch.tensor([w, h, w, h], dtype=loc.dtype, device=loc.device)
    results = []
    for b in range(loc.shape[0]):
        kept = []
        for c in range(probs.shape[-1]):
            idx = (probs[b, :, c] > score_thresh).nonzero().squeeze(1)
            idx = idx[probs[b, idx, c].topk(min(top_k, len(idx))).indices]
            boxes = torch.minimum(decode_boxes(loc[b, idx], anchors_t[idx], variances).clamp(min=0), limits)
            keep = nms(boxes, probs[b, idx, c], nms_iou)
            kept.append((boxes[keep], probs[b, idx[keep], c], torch.full_like(keep, c)))
        boxes, scores, labels = (torch.cat(parts) for parts in zip(*kept))
        order = torch.sort(scores, descending=True, stable=True).indices[:max_detections]
        results.append({"boxes": boxes[order], "scores": scores[order], "labels": labels[order]})
    return results
