"""YOLACT inference: mask assembly and decoding of the head's maps into per-image instances (Fast NMS is the
shared one of :mod:`ablate.tasks.boxes`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ablate.tasks.boxes import VARIANCES, decode_boxes, fast_nms, flatten_levels
from ablate.tasks.yolact.anchors import Anchors, box_region


def assemble_masks(
    proto: Tensor, coef: Tensor, boxes: Tensor, image_size: tuple[int, int], threshold: float = 0.5
) -> Tensor:
    """YOLACT mask assembly: sigmoid(proto @ coef) at prototype resolution, bilinear upsampling to the input
    size, crop to the detection box (pixels outside set to 0), threshold. ``proto`` [k, Hp, Wp], ``coef`` [n, k],
    ``boxes`` [n, 4] xyxy input pixels -> [n, H, W] bool. Cropping after upsampling keeps the crop exact."""
    if coef.shape[0] == 0:
        return torch.zeros(0, *image_size, dtype=torch.bool, device=proto.device)
    masks = torch.sigmoid(torch.einsum("khw,nk->nhw", proto, coef))
    masks = F.interpolate(masks[None], image_size, mode="bilinear", align_corners=False)[0]
    return (masks * box_region(boxes, *image_size)) > threshold


@torch.no_grad()
def decode(
    outputs: dict,
    image_size: tuple[int, int],
    score_thresh: float = 0.05,
    nms_iou: float = 0.5,
    top_k: int = 200,
    max_detections: int = 100,
    anchors: Anchors | None = None,
    variances: tuple[float, float] = VARIANCES,
) -> list[dict[str, Tensor]]:
    """Head maps -> one dict per image in :class:`~ablate.metrics.coco.MaskAP`'s format: ``masks`` (N, H, W)
    bool, ``scores`` (N,), ``labels`` (N,) in [0, K), ``boxes`` (N, 4) xyxy pixels clipped to the image.

    Class scores are softmax probabilities without the background column; anchors whose best class score is not
    above ``score_thresh`` are dropped before :func:`fast_nms`. ``anchors`` must match the head's (default: the
    default :class:`Anchors`)."""
    anchors_gen = anchors or Anchors()
    a = anchors_gen.num_per_location
    proto = outputs["proto"]
    if outputs["box"][0].shape[1] != 4 * a:
        raise ValueError(f"decode: box maps have {outputs['box'][0].shape[1]} channels, anchors expect {4 * a}")
    probs = flatten_levels(outputs["cls"], outputs["cls"][0].shape[1] // a).softmax(-1)[..., 1:]
    loc = flatten_levels(outputs["box"], 4)
    coef = flatten_levels(outputs["coef"], proto.shape[1])
    anchors_t = anchors_gen(image_size, [tuple(m.shape[-2:]) for m in outputs["cls"]], loc.device)
    h, w = image_size
    limits = torch.tensor([w, h, w, h], dtype=loc.dtype, device=loc.device)
    results = []
    for b in range(loc.shape[0]):
        cand = (probs[b].max(1).values > score_thresh).nonzero().squeeze(1)
        boxes = decode_boxes(loc[b][cand], anchors_t[cand], variances)
        boxes = torch.minimum(boxes.clamp(min=0), limits)
        keep, labels, scores = fast_nms(boxes, probs[b][cand], nms_iou, score_thresh, top_k, max_detections)
        boxes = boxes[keep]
        results.append(
            {
                "masks": assemble_masks(proto[b], coef[b][cand][keep], boxes, image_size),
                "scores": scores,
                "labels": labels,
                "boxes": boxes,
            }
        )
    return results
