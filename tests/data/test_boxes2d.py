"""boxes2d carries KITTI's ignored types (Van, Person_sitting, DontCare) after the classes, as KittiAP reads them."""

from collections import Counter

import torch

from ablate.data.datamodule import KittiDataModule
from ablate.data.dataset import BOX_LABELS, CLASSES
from ablate.metrics.kitti import LABEL_NAMES


def test_box_labels_are_the_metrics_label_names():
    assert BOX_LABELS == LABEL_NAMES and BOX_LABELS[:3] == CLASSES


def test_real_kitti_boxes_keep_dontcare_and_drop_other_types(kitti_root, tmp_path):
    dm = KittiDataModule(
        root=str(kitti_root / "object"), data_dir=str(tmp_path), modalities=["rgb"], targets=["boxes2d"], batch_size=8
    )
    dm.setup()
    boxes = [ds[i]["boxes2d"] for ds in dm.datasets.values() for i in range(len(ds))]
    counts = Counter(BOX_LABELS[k] for b in boxes for k in b["labels"].tolist())
    # the 8 frames' label files: 12 Car, 2 Pedestrian, 2 Cyclist, 19 DontCare, 1 Truck, 1 Misc
    assert counts == {"Car": 12, "Pedestrian": 2, "Cyclist": 2, "DontCare": 19}
    dontcare = torch.cat([b["difficulty"][b["labels"] == 5] for b in boxes])
    assert (dontcare == -1).all() and len(dontcare) == 19
    assert all(b["boxes"].shape == (len(b["labels"]), 4) for b in boxes)
