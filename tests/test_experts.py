"""The frozen experts' feature cache of two-stage training (ablate.jobs.experts.FeatureCache, SMoE §4.3): same loss,
outputs and gradients as running the experts, the experts not run on a cached step, and on only where valid."""

from __future__ import annotations

import functools

import lightning as L
import pytest
import torch
from omegaconf import OmegaConf

from ablate.fusion import FusionModel, build
from ablate.jobs.experts import FeatureCache, feature_cache
from ablate.tasks.instance import InstanceTask, YolactHead

MODALITIES = {"rgb": 3, "ddm_jet": 3}
SIZE = (64, 64)
ADAM = functools.partial(torch.optim.Adam, lr=1e-3)


def tiny(stage: str, single: str | None = None) -> FusionModel:
    return FusionModel(
        stage=stage,
        modalities=MODALITIES,
        single=single,
        fusion=functools.partial(build, name="smoe"),
        head=functools.partial(YolactHead, num_classes=2, num_prototypes=4),
        backbone={"depth": 18, "width": 0.125},
        fpn_channels=16,
    )


def stage2(stage: str, freeze: bool = True) -> FusionModel:
    """A fused model on experts that differ from its own initialisation, loaded as in ablate.jobs.experts.attach."""
    torch.manual_seed(0)
    model = tiny(stage)
    for m in MODALITIES:
        expert = tiny("single", m)
        for _ in range(2):  # a few steps so the experts' BatchNorm statistics are not the defaults
            expert(batch(["a", "b"], seed=7))
        model.load_expert(m, expert, freeze=freeze)
    return model.train()


def batch(frames: list[str], seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    n = len(frames)
    box = torch.tensor([[8.0, 16.0, 40.0, 48.0]])
    mask = torch.zeros(1, *SIZE, dtype=torch.bool)
    mask[:, 16:48, 8:40] = True
    return {
        "rgb": torch.rand(n, 3, *SIZE, generator=g),
        "ddm_jet": torch.rand(n, 3, *SIZE, generator=g),
        "instances": [{"masks": mask, "labels": torch.tensor([0]), "boxes": box} for _ in range(n)],
        "ignore": torch.zeros(n, *SIZE, dtype=torch.bool),
        "frame": list(frames),
    }


def calls(model: FusionModel) -> list[str]:
    """Names of the frozen parts, appended each time one runs."""
    seen: list[str] = []
    for name, part in [*model.encoders.items(), *getattr(model, "fpns", {}).items()]:
        part.register_forward_hook(lambda *_, name=name: seen.append(name))
    return seen


def loss_and_grads(task: InstanceTask, b: dict) -> tuple[dict, torch.Tensor, dict[str, torch.Tensor]]:
    task.zero_grad(set_to_none=True)
    outputs = task(b)
    loss = task.criterion(outputs, task.targets(b), SIZE)["total"]
    loss.backward()
    grads = {k: p.grad.clone() for k, p in task.named_parameters() if p.requires_grad}
    return outputs, loss.detach(), grads


@pytest.mark.parametrize("stage", ["backbone", "fpn", "late"])
def test_a_cached_step_equals_running_the_experts_and_does_not_run_them(stage):
    task = InstanceTask(stage2(stage), ADAM)
    seen = calls(task.model)
    b = batch(["000001", "000002", "000003"])
    ref_out, ref_loss, ref_grads = loss_and_grads(task, b)
    assert seen  # without the cache every step runs the experts
    task.feature_cache = FeatureCache()
    loss_and_grads(task, b)  # cold: computes and stores the features
    assert task.feature_cache.misses == 3 and len(task.feature_cache.frames) == 3
    seen.clear()
    shuffled = batch(["000003", "000001", "000002"])
    shuffled.update({k: b[k][[2, 0, 1]] for k in ("rgb", "ddm_jet")})
    out, loss, grads = loss_and_grads(task, shuffled)  # warm, frames in another order
    assert seen == [] and task.feature_cache.hits == 3
    torch.testing.assert_close(loss, ref_loss)
    torch.testing.assert_close(out["proto"], ref_out["proto"][[2, 0, 1]])
    torch.testing.assert_close(out["cls"][0], ref_out["cls"][0][[2, 0, 1]])
    assert grads.keys() == ref_grads.keys() and grads
    for k in grads:
        torch.testing.assert_close(grads[k], ref_grads[k], atol=1e-5, rtol=1e-4, msg=k)


def test_the_experts_run_on_the_frames_not_in_the_cache_only():
    model = stage2("fpn")
    cache, ab = FeatureCache(), batch(["a", "b"])
    cache(model, ab)
    sizes: list[int] = []
    model.encoders["rgb"].register_forward_hook(lambda _, inputs, __: sizes.append(len(inputs[0])))
    b = batch(["b", "c", "a"], seed=1)
    for m in MODALITIES:  # frames a and b with their inputs, c new
        b[m][0], b[m][2] = ab[m][1], ab[m][0]
    features = cache(model, b)
    assert sizes == [1] and set(cache.frames) == {"a", "b", "c"} and (cache.hits, cache.misses) == (2, 3)
    expected = model.frozen_features(b)
    for m in MODALITIES:
        for got, want in zip(features[m], expected[m]):
            torch.testing.assert_close(got, want)
    per_frame = sum(p[0].numel() * 4 for m in MODALITIES for p in features[m])  # float32, P3..P7 per modality
    assert cache.nbytes == 3 * per_frame
    with pytest.raises(KeyError, match="frame"):
        cache(model, {k: v for k, v in batch(["a"]).items() if k != "frame"})


def test_frames_beyond_the_memory_cap_are_not_stored_and_run_every_step():
    model = stage2("fpn")
    one = sum(p[0].numel() * 4 for m in MODALITIES for p in model.frozen_features(batch(["a"]))[m])
    cache = FeatureCache(max_bytes=2.5 * one)
    b = batch(["a", "b", "c"])
    first = cache(model, b)
    assert list(cache.frames) == ["a", "b"] and cache.nbytes == 2 * one
    again = cache(model, b)
    assert (cache.hits, cache.misses) == (2, 4)
    for m in MODALITIES:
        for x, y in zip(first[m], again[m]):
            torch.testing.assert_close(x, y)


@pytest.mark.parametrize(
    "stage,freeze,switch,on",
    [
        ("fpn", True, True, True),
        ("backbone", True, True, True),
        ("late", True, True, True),
        ("fpn", False, True, False),
        ("fpn", True, False, False),
        ("early", True, True, False),
        ("single", True, True, False),
    ],
)
def test_the_cache_is_on_only_for_frozen_experts_at_a_fusion_stage(stage, freeze, switch, on):
    cfg = OmegaConf.create({"experts": {"freeze": freeze, "cache_features": switch, "cache_max_gb": 8}})
    if stage == "early":
        model = tiny("early")
    elif stage == "single":
        model = tiny("single", "rgb")
        model.load_expert("rgb", tiny("single", "rgb"), freeze=freeze)
    else:
        model = stage2(stage, freeze)
    assert (feature_cache(cfg, model) is not None) is on
    assert not on or feature_cache(cfg, model).max_bytes == 8 * 2**30
    assert feature_cache(OmegaConf.create({"experts": None}), model) is None
    assert model.cacheable is (on or not switch)
    if not model.cacheable and stage != "early":
        with pytest.raises(ValueError, match="frozen"):
            model.frozen_features(batch(["a"]))


def test_a_fit_fills_the_cache_in_the_first_epoch_and_reads_it_afterwards(tmp_path):
    task = InstanceTask(stage2("fpn"), ADAM)
    task.feature_cache = FeatureCache()
    train = [batch(["t0", "t1"], 1), batch(["t2", "t3"], 2)]
    val = [batch(["v0", "v1"], 3)]
    trainer = L.Trainer(
        max_epochs=2,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        default_root_dir=tmp_path,
    )
    seen = calls(task.model)
    loader = functools.partial(torch.utils.data.DataLoader, batch_size=None)
    trainer.fit(task, loader(train), loader(val))
    assert sorted(task.feature_cache.frames) == ["t0", "t1", "t2", "t3", "v0", "v1"]
    assert (task.feature_cache.misses, task.feature_cache.hits) == (6, 6)  # epoch 2 reads train and val frames
    assert len(seen) == 3 * 4  # 3 first batches x (2 encoders + 2 FPNs); none in epoch 2


def test_on_a_gpu_the_cache_is_kept_there_where_the_features_fit_and_turned_off_where_not(monkeypatch, caplog):
    gib = 2**30
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (10 * gib, 80 * gib))
    gpu = torch.device("cuda", 0)
    fits = FeatureCache(fit_frames=1000)
    assert fits._place(gpu, 4 * 2**20) == gpu and not fits.off  # 3.9 GiB of the 5 GiB half of the free memory
    assert FeatureCache()._place(gpu, 4 * 2**20) == torch.device("cpu")  # frames unknown: the CPU, as before
    assert FeatureCache(fit_frames=10**6)._place(torch.device("cpu"), 4 * 2**20) == torch.device("cpu")
    too_big = FeatureCache(fit_frames=5985)
    with caplog.at_level("INFO", logger="ablate.jobs.experts"):
        too_big._place(gpu, 19 * 2**20)  # SMoE's P3-P7 at scale=paper: 111 GiB
    assert too_big.off
    assert [r.getMessage() for r in caplog.records if "cache_features is off" in r.getMessage()] == [
        "experts.cache_features is off: the frozen experts' features of 5985 frames (19.0 MiB a frame, 111.0 GiB) "
        "exceed 50 % of the 10.0 GiB free on cuda:0; the experts run every step"
    ]
    model, b = stage2("fpn"), batch(["a", "b"])
    features = too_big(model, b)  # off: the experts run, nothing is stored
    assert not too_big.frames and too_big.nbytes == 0
    for m in MODALITIES:
        for got, want in zip(features[m], model.frozen_features(b)[m]):
            torch.testing.assert_close(got, want)
