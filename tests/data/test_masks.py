"""Instance masks from LiDAR + 3D boxes (ablate.data.masks) on the real KITTI sample frames, the dataset's use of
them when a folder has no instance_2/, and the instance task trained on them at scale=smoke."""

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from ablate.data import DataError
from ablate.data.dataset import KittiDataset
from ablate.data.kitti import Calibration, list_frames, read_image, read_labels, read_velodyne
from ablate.data.masks import from_lidar, instance_map
from tests.scaleout import ablate


@pytest.fixture(scope="module")
def obj(kitti_root):
    return kitti_root / "object" / "training"


@pytest.fixture(scope="module")
def frames(obj):
    """frame -> (points, calib, objects, shape, masks) for every shared object frame."""
    out = {}
    for f in list_frames(obj):
        calib, points = Calibration.from_file(obj / "calib" / f"{f}.txt"), read_velodyne(obj / "velodyne" / f"{f}.bin")
        objects, shape = read_labels(obj / "label_2" / f"{f}.txt"), read_image(obj / "image_2" / f"{f}.png").shape[:2]
        out[f] = points, calib, objects, shape, from_lidar(points, calib, objects, shape)
    return out


def box_iou(a, b) -> float:
    inter = max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_unoccluded_cars_fill_their_2d_box(frames):
    cars = 0
    for f, (_, _, objects, shape, masks) in frames.items():
        assert masks.shape == (len(objects), *shape) and masks.dtype == bool
        for o, m in zip(objects, masks):
            if o.type != "Car" or o.occluded != 0 or o.truncated > 0.15:
                continue
            cars += 1
            ys, xs = np.nonzero(m)
            assert len(ys), (f, o.bbox)
            x0, y0, x1, y1 = o.bbox
            assert xs.min() >= np.floor(x0) and xs.max() <= np.ceil(x1), (f, o.bbox)  # inside the 2D box
            assert ys.min() >= np.floor(y0) and ys.max() <= np.ceil(y1), (f, o.bbox)
            iou = box_iou((xs.min(), ys.min(), xs.max() + 1, ys.max() + 1), o.bbox)
            assert iou >= 0.5, (f, o.bbox, iou)
    assert cars == 10


def test_masks_never_overlap_and_dontcare_is_empty(frames):
    for f, (_, _, objects, _, masks) in frames.items():
        assert masks.sum(0).max() <= 1, f
        for o, m in zip(objects, masks):
            if o.type == "DontCare":
                assert not m.any(), f
            else:  # every 3D box of these frames holds LiDAR points in its 2D box
                assert m.any(), (f, o.type)


def test_masks_follow_the_order_of_objects(frames):
    points, calib, objects, shape, masks = frames["000006"]
    again = from_lidar(points, calib, objects[::-1], shape)
    np.testing.assert_array_equal(again, masks[::-1])
    assert from_lidar(points, calib, [], shape).shape == (0, *shape)
    ids = instance_map(masks)
    assert ids.dtype == np.uint16
    for k, m in enumerate(masks):
        np.testing.assert_array_equal(ids == k + 1, m)


def test_dataset_derives_instances_from_lidar_and_caches_them(obj, frames, tmp_path):
    ds = KittiDataset(obj, ["000006", "000007"], ["rgb"], ["instances", "road_objects"], ["clear"], cache_dir=tmp_path)
    sample = ds[0]
    _, _, objects, _, masks = frames["000006"]
    inst = sample["instances"]
    assert inst["labels"].tolist() == [0, 0, 0, 0]  # the four cars of 000006, in label order
    assert torch.equal(inst["masks"], torch.from_numpy(masks[:4]))
    assert torch.equal(inst["boxes"], torch.tensor([o.bbox for o in objects[:4]], dtype=torch.float32))
    assert torch.equal(sample["road_objects"][0] > 0, torch.from_numpy(masks.any(0)))
    hits = ds.cache_hits
    assert torch.equal(ds[0]["instances"]["masks"], inst["masks"]) and ds.cache_hits > hits


def test_no_masks_and_nothing_to_derive_them_from_is_a_data_error(obj, tmp_path):
    for sub in ("image_2", "calib"):  # links, not copies
        (tmp_path / sub).symlink_to(obj / sub)
    with pytest.raises(DataError, match=r"'instances'.*no instance_2/.*velodyne/ and label_2/"):
        KittiDataset(tmp_path, ["000000"], ["rgb"], ["instances"], ["clear"])


def test_instance_task_trains_on_real_kitti_at_smoke_scale(kitti_root, tmp_path):
    out = ablate(
        tmp_path,
        "data=kitti",
        f"data.root={kitti_root / 'object'}",
        "scale=smoke",
        "experts=null",
        "data.batch_size=2",
        "data.limit_frames={train:2,val:1,test:1}",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "task.figure_frames=1",
        "comp_time.warmup=0",
        "comp_time.repeats=1",
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    (run,) = client.search_runs([client.get_experiment_by_name("ablate").experiment_id], "tags.kind = 'job'")
    assert run.info.status == "FINISHED" and "map" in run.data.metrics and np.isfinite(run.data.metrics["loss"])
    assert list((tmp_path / "data" / "cache").glob("*/instances-*/*.npy"))  # the masks came from from_lidar
