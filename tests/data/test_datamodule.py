"""KittiDataModule: batch shapes and value ranges, cache hits, conditions spread, missing targets."""

import pytest
import torch

from ablate.data.datamodule import KittiDataModule

ALL_MODALITIES = ["rgb", "intensity", "sparse_depth", "dense_depth", "ddm_jet", "dhi", "bev"]
ALL_TARGETS = ["free_space", "road_objects", "semantic", "instances", "boxes2d", "road_bev"]
SMALL = {"frames": 10, "seed": 1, "height": 64, "width": 208}


@pytest.fixture(scope="module")
def dm(tmp_path_factory):
    dm = KittiDataModule(
        synth=SMALL,
        data_dir=str(tmp_path_factory.mktemp("data")),
        modalities=ALL_MODALITIES,
        targets=ALL_TARGETS,
        conditions=["clear", "night", "rain_day", "rain_night", "glare"],
        batch_size=3,
    )
    dm.prepare_data()
    dm.setup()
    return dm


def test_batch_shapes_and_ranges(dm):
    b = next(iter(dm.train_dataloader()))
    h, w = 64, 208
    assert dm.channels == {
        "rgb": 3,
        "intensity": 1,
        "sparse_depth": 1,
        "dense_depth": 1,
        "ddm_jet": 3,
        "dhi": 3,
        "bev": 6,
    }
    for m, c in dm.channels.items():
        size = (80, 40) if m == "bev" else (h, w)
        assert b[m].shape == (3, c, *size) and b[m].dtype == torch.float32, m
    for m in ("rgb", "intensity", "ddm_jet", "dhi", "sparse_depth"):
        assert 0 <= b[m].min() and b[m].max() <= 1.6, m
    assert (b["dense_depth"] > 0).all()
    assert b["free_space"].shape == b["road_objects"].shape == (3, 1, h, w)
    assert b["semantic"].dtype == torch.int64 and set(b["semantic"].unique().tolist()) <= {0, 1, 2}
    assert ((b["semantic"] == 2) == (b["road_objects"][:, 0] > 0)).all()
    assert b["road_bev"].shape == (3, 1, 80, 40) and b["road_bev"].sum() > 0
    assert b["ignore"].shape == (3, h, w) and b["ignore"].dtype == torch.bool
    assert len(b["frame"]) == len(b["condition"]) == len(b["instances"]) == len(b["boxes2d"]) == 3
    for inst, box in zip(b["instances"], b["boxes2d"]):
        n = len(inst["labels"])
        assert inst["masks"].shape == (n, h, w) and inst["boxes"].shape == (n, 4)
        assert box["boxes"].shape == (len(box["labels"]), 4) and box["difficulty"].shape == box["labels"].shape


def test_cache_hit_on_second_access(dm):
    ds = dm.datasets["val"]
    first = ds[0]
    hits, misses = ds.cache_hits, ds.cache_misses
    second = ds[0]
    assert ds.cache_misses == misses and ds.cache_hits > hits
    for m in ALL_MODALITIES:
        assert torch.equal(first[m], second[m]), m


def test_conditions_spread_and_fixed_split(dm):
    conds = [dm.datasets["train"][i]["condition"] for i in range(len(dm.datasets["train"]))]
    assert len(conds) == 6 and len(set(conds)) == 5
    assert sum(len(d) for d in dm.datasets.values()) == SMALL["frames"]


def test_corruption_applied_to_named_modality(tmp_path, dm):
    kw = dict(synth=SMALL, data_dir=dm.data_dir, modalities=["rgb", "dense_depth"], batch_size=2)
    plain = KittiDataModule(**kw)
    blank = KittiDataModule(**kw, corruption={"name": "blank", "modality": "dense_depth"})
    a, b = (next(iter(d.test_dataloader())) for d in (plain, blank))
    assert torch.equal(a["rgb"], b["rgb"]) and not b["dense_depth"].any() and a["dense_depth"].all()


def test_real_kitti_object(kitti_root, tmp_path):
    dm = KittiDataModule(
        root=str(kitti_root / "object"),
        data_dir=str(tmp_path),
        modalities=["rgb", "dhi"],
        targets=["boxes2d"],
        batch_size=2,
        limit_frames={"train": 2},
    )
    b = next(iter(dm.train_dataloader()))
    assert b["rgb"].shape == (2, 3, 370, 1224) and b["dhi"].shape == (2, 3, 370, 1224)
    # Instance masks come from the LiDAR and the 3D boxes there (tests/data/test_masks.py).
    # LiDAR weather: its own per-frame condition, its own cache entries; fog thins the scan.
    fog = KittiDataModule(
        root=str(kitti_root / "object"),
        data_dir=str(tmp_path),
        modalities=["sparse_depth"],
        batch_size=2,
        limit_frames={"train": 2},
        lidar_weather=["fog"],
    )
    clear = KittiDataModule(
        root=str(kitti_root / "object"),
        data_dir=str(tmp_path),
        modalities=["sparse_depth"],
        batch_size=2,
        limit_frames={"train": 2},
    )
    f, c = (next(iter(d.train_dataloader())) for d in (fog, clear))
    assert f["lidar_condition"] == ["fog", "fog"] and "lidar_condition" not in c
    assert (f["sparse_depth"] > 0).sum() < 0.9 * (c["sparse_depth"] > 0).sum()
    with pytest.raises(KeyError, match="unknown LiDAR weather 'snow'"):
        KittiDataModule(root=str(kitti_root / "object"), data_dir=str(tmp_path), lidar_weather=["snow"]).setup()
    with pytest.raises(KeyError, match="valid: rgb"):
        KittiDataModule(modalities=["lidar"])


def test_unknown_generator_version_is_one_clear_error(tmp_path):
    from ablate.data import DataError
    from ablate.data.datamodule import ensure_synth

    with pytest.raises(DataError, match=r"data.synth.version=1: this ablate generates version 2"):
        ensure_synth(tmp_path, {"frames": 2, "version": 1})
    assert not any(tmp_path.iterdir())  # nothing generated


def test_an_empty_split_is_one_clear_error_naming_it(dm):
    from ablate.data import DataError

    small = KittiDataModule(synth=SMALL, data_dir=dm.data_dir, modalities=["rgb"], limit_frames={"val": 0})
    assert len(small.train_dataloader()) > 0
    with pytest.raises(
        DataError,
        match=r"the val split has no frames \(8 in all, data.limit_frames.val=0\); "
        r"list them in .*ImageSets/val.txt",
    ):
        small.val_dataloader()


def test_jobs_starting_together_generate_the_dataset_once(tmp_path, monkeypatch):
    """The jobs of a parallel sweep on a fresh machine: one generates the dataset, the others wait and read it."""
    import threading
    import time

    from ablate.data import datamodule

    calls = []
    real = datamodule.generate

    def slow_generate(out, *args, **kwargs):
        calls.append(out)
        time.sleep(0.5)  # long enough for the other job to arrive while this one writes
        return real(out, *args, **{**kwargs, "workers": 1, "progress": False})

    monkeypatch.setattr(datamodule, "generate", slow_generate)
    found = []
    jobs = [
        threading.Thread(target=lambda: found.append(datamodule.ensure_synth(tmp_path, {"frames": 2})))
        for _ in range(2)
    ]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join()
    assert len(calls) == 1 and len(found) == 2 and found[0] == found[1]
    assert (found[0] / "synth.json").is_file() and len(list((found[0] / "image_2").glob("*.png"))) == 2


def _fill_cache(cache_dir, seed, out):
    """One job's first use of a cache entry, numpy's global rng seeded as ``L.seed_everything`` seeds it."""
    import time
    from types import SimpleNamespace

    import numpy as np

    from ablate.data.dataset import KittiDataset

    np.random.seed(seed)
    job = SimpleNamespace(cache_dir=cache_dir, cache_hits=0, cache_misses=0)

    def compute():
        time.sleep(0.3)  # both jobs compute before either stores; 32 MB take long enough to write to overlap
        return np.full(4_000_000, 7.0)

    try:
        value = KittiDataset._cached(job, "000006", "dense_depth", {"shape": [2, 2]}, compute)
        out.put([value.size, float(value.min()), float(value.max())])
    except Exception as err:
        out.put(repr(err))


def test_parallel_jobs_seeded_alike_store_one_cache_entry_without_clashing(tmp_path):
    """Two jobs of a parallel sweep, seeded alike, fill the same cache entry at once: each writes its own temporary
    file and renames it into place, so neither finds its file taken by the other."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    jobs = [ctx.Process(target=_fill_cache, args=(tmp_path, 0, out)) for _ in range(2)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(30)
    assert [out.get(timeout=5) for _ in jobs] == [[4_000_000, 7.0, 7.0]] * 2
    assert [p.name for p in tmp_path.rglob("*.npy")] == ["000006.npy"]


def test_the_jobs_seed_orders_the_training_frames_and_leaves_the_test_set_alone(dm, tmp_path):
    """What a seed randomises (docs/verdicts.md): the training frames' order follows ``order_seed`` (the job's
    seed); the frames, their conditions and the validation and test batches do not."""

    def module(order_seed):
        other = KittiDataModule(
            synth=SMALL, data_dir=dm.data_dir, modalities=["rgb"], targets=["semantic"], batch_size=1,
            conditions=["clear", "night", "rain_day", "rain_night", "glare"], order_seed=order_seed,
        )  # fmt: skip
        other.setup()
        return other

    def order(m, split):
        loader = m.train_dataloader() if split == "train" else m.test_dataloader()
        return [b["frame"][0] for b in loader]

    a, b, again = module(0), module(1), module(0)
    assert order(a, "train") == order(again, "train") and order(a, "train") != order(b, "train")
    assert sorted(order(a, "train")) == sorted(order(b, "train"))  # the same frames, another order
    assert order(a, "test") == order(b, "test")
    for split in ("train", "test"):
        conditions = [[x["condition"] for x in m.datasets[split]] for m in (a, b)]
        assert conditions[0] == conditions[1]
