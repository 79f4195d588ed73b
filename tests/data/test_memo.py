"""Decoded frames kept between epochs (ablate.data.memo, ``data.memo_gb``): the same samples without the files read
again, a copy per read, bounded, off with augmentation and in loader workers; a job's numbers and config hash are
those of a job without it."""

from pathlib import Path

import pytest
import torch

from ablate.config import compose
from ablate.data import dataset as dataset_module
from ablate.data import memo as memo_module
from ablate.data.datamodule import KittiDataModule
from ablate.data.memo import FrameMemo, tensor_bytes
from ablate.store.identity import config_hash
from tests.scaleout import TINY, ablate, output, runs

SMALL = {"frames": 10, "seed": 1, "height": 64, "width": 208}
KINDS = dict(
    modalities=["rgb", "dense_depth", "bev"],
    targets=["semantic", "instances", "boxes2d", "road_bev"],
    conditions=["clear", "night", "rain_day"],
    corruption={"name": "noise", "modality": "rgb", "p": 0.5},
)


def module(data_dir: Path, memo_gb: float, **extra) -> KittiDataModule:
    dm = KittiDataModule(synth=SMALL, data_dir=str(data_dir), batch_size=2, memo_gb=memo_gb, **KINDS, **extra)
    dm.setup()
    return dm


def same(a, b) -> bool:
    """Nested samples equal, tensor for tensor."""
    if torch.is_tensor(a):
        return torch.is_tensor(b) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def test_a_kept_frame_is_the_frame_read_from_its_files_and_no_file_is_read_again(data_dir, monkeypatch):
    plain, kept = module(data_dir, 0).datasets["train"], module(data_dir, 1).datasets["train"]
    first = [kept[i] for i in range(len(kept))]
    reads: list[Path] = []
    real = dataset_module.kitti.read_image
    monkeypatch.setattr(dataset_module.kitti, "read_image", lambda path: reads.append(path) or real(path))
    again = [kept[i] for i in range(len(kept))]
    assert not reads and kept.memo is not None and kept.memo.hits == len(kept)  # the second epoch reads no file
    assert all(same(a, b) for a, b in zip(again, first))
    assert all(same(plain[i], again[i]) for i in range(len(kept)))  # what the files give without it
    assert len(reads) == len(plain)  # and without it every read reads the files


def test_a_caller_changing_a_sample_in_place_does_not_change_the_next_read(data_dir):
    ds = module(data_dir, 1).datasets["train"]
    before = ds[0]
    ds[0]["rgb"].zero_()  # the first read (kept) and a later one (from the memo), each changed by its caller
    after = ds[0]
    after["rgb"].zero_()
    after["instances"]["boxes"].add_(7)
    assert same(ds[0], before)


def test_the_memo_keeps_frames_up_to_its_bound_and_reads_the_rest_each_time(data_dir):
    ds = module(data_dir, 0).datasets["train"]
    one = tensor_bytes(ds[0])
    ds.memo = FrameMemo(1.5 * one)  # room for one frame of this size
    for _ in range(2):
        for i in range(3):
            ds[i]
    assert list(ds.memo.samples) == [0] and ds.memo.nbytes == one <= ds.memo.max_bytes
    assert ds.memo.hits == 1 and ds.memo.misses == 5


def test_the_memo_keeps_no_frame_the_machine_has_no_memory_to_spare_for(data_dir, monkeypatch):
    ds = module(data_dir, 1).datasets["train"]
    one = tensor_bytes(ds[0])
    monkeypatch.setattr(memo_module, "spare_bytes", lambda: 1.5 * one)  # room for one more frame on this machine
    ds[1]
    monkeypatch.setattr(memo_module, "spare_bytes", lambda: 0.5 * one)  # then none
    ds[2]
    assert sorted(ds.memo.samples) == [0, 1]


def test_the_frames_a_fit_kept_are_let_go_when_it_ends(data_dir):
    dm = module(data_dir, 1)
    for split in ("train", "val"):
        for _batch in getattr(dm, f"{split}_dataloader")():
            pass
    assert all(len(dm.datasets[s].memo.samples) == len(dm.datasets[s]) for s in ("train", "val"))
    dm.teardown("test")  # a test leaves them (the test split keeps none)
    assert dm.datasets["train"].memo.nbytes > 0
    dm.teardown("fit")  # Lightning's call once trainer.fit ends
    assert all(dm.datasets[s].memo.nbytes == 0 and not dm.datasets[s].memo.samples for s in ("train", "val"))


def test_the_memo_is_off_for_augmented_training_frames_the_test_split_and_in_loader_workers(data_dir, monkeypatch):
    dm = module(data_dir, 1, augment={"flip": 0.5})
    assert dm.datasets["train"].memo is None and dm.datasets["val"].memo is not None
    assert dm.datasets["test"].memo is None  # read once
    val = dm.datasets["val"]
    monkeypatch.setattr(dataset_module, "get_worker_info", lambda: object())  # as inside a loader worker
    val[0]
    assert not val.memo.samples and val.memo.misses == 0


def test_the_memo_is_an_option_of_the_data_and_leaves_the_config_hash_alone():
    on, off = (compose(["experiment=chinet_table2", "row=unet", f"data.memo_gb={gb}"]) for gb in (2, 0))
    assert compose(["experiment=chinet_table2", "row=unet"]).data.memo_gb == 2
    assert config_hash(on) == config_hash(off)


def test_a_jobs_numbers_are_the_same_with_frames_kept_and_without(tmp_path):
    """Three epochs of a smoke job, once with every frame kept and once with none: the same metrics per epoch."""
    found = {}
    for gb in (0, 2):
        cwd = tmp_path / f"memo{gb}"
        cwd.mkdir()
        out = ablate(cwd, "experiment=chinet_table2", "row=unet", *TINY, "trainer.max_epochs=3", f"data.memo_gb={gb}")
        assert out.returncode == 0, output(out)
        client, (job,) = runs(f"sqlite:///{cwd / 'mlflow.db'}", "chinet_table2")
        curves = {k: [m.value for m in client.get_metric_history(job.info.run_id, k)] for k in ("val/loss", "loss")}
        assert len(curves["val/loss"]) == 3
        found[gb] = (job.data.metrics, curves)
    assert found[0] == found[2]
