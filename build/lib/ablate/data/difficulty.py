"""Which ground-truth objects are tall enough to count, at any image height: the rule the mask AP
(:class:`ablate.metrics.coco.MaskAP`), KITTI's AP (:class:`ablate.metrics.kitti.KittiAP`) and the dataset statistics
(:mod:`ablate.data.stats`) share. It lives with the data, below the metrics, so that both can import it."""

from __future__ import annotations

from torch import Tensor

#: SMoE §5 / KITTI moderate: objects at least this many px tall at ``REFERENCE_HEIGHT`` count.
MIN_HEIGHT, REFERENCE_HEIGHT = 25.0, 375.0


def counted(
    heights: Tensor, image_height: float, min_height: float = MIN_HEIGHT, reference_height: float = REFERENCE_HEIGHT
) -> Tensor:
    """Which ground truths of box heights ``heights`` (px) count in an image ``image_height`` px tall: the
    threshold ``min_height`` scales with ``image_height / reference_height``."""
    return heights >= min_height * image_height / reference_height
