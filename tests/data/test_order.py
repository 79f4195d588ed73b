"""A job resumed from its checkpoint trains on what the uninterrupted job trained on (ablate.data.order,
ablate.jobs.generators): the same frames in the same order, the same global draws, the same weights."""

import shutil

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from ablate.data.order import ResumableLoader, trained_batches
from ablate.jobs.generators import GlobalGenerators


class Frames(Dataset):
    """Ten frames; with ``augment``, each draws from torch's global generator as augmentation does."""

    def __init__(self, augment: bool) -> None:
        self.augment = augment

    def __len__(self) -> int:
        return 10

    def __getitem__(self, i: int) -> torch.Tensor:
        jitter = torch.rand(1) if self.augment else torch.zeros(1)
        return torch.tensor([float(i)]) + jitter


class Net(L.LightningModule):
    """A linear model behind dropout (torch's global generator), recording the frames of each batch it trains on."""

    def __init__(self, augment: bool, seen: list) -> None:
        super().__init__()
        self.layer, self.drop, self.augment, self.seen = torch.nn.Linear(1, 1), torch.nn.Dropout(0.5), augment, seen

    def training_step(self, batch, batch_idx):
        self.seen.append((self.current_epoch, batch.floor().flatten().tolist()))
        return self.layer(self.drop(batch)).pow(2).mean()

    def validation_step(self, batch, batch_idx):
        self.log("val", self.layer(batch).mean())

    def val_dataloader(self):
        return DataLoader(Frames(False), 5)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)

    def train_dataloader(self):
        generator = torch.Generator().manual_seed(3)
        return ResumableLoader(Frames(self.augment), 3, generator, lambda: trained_batches(self.trainer))


class Copy(L.Callback):
    """Saves a checkpoint at (epoch, batch) the way a stop does, or copies last.ckpt after an epoch's validation."""

    def __init__(self, at: tuple[int, int] | None, epoch_end: int | None, path) -> None:
        self.at, self.epoch_end, self.path = at, epoch_end, path

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        if self.at == (trainer.current_epoch, batch_idx):
            trainer.save_checkpoint(self.path)

    def on_train_epoch_start(self, trainer, module):  # last.ckpt is written after every on_train_epoch_end
        if self.epoch_end is not None and trainer.current_epoch == self.epoch_end + 1:
            shutil.copy(trainer.checkpoint_callback.last_model_path, self.path)


def fit(tmp_path, augment: bool, epochs: int, ckpt=None, copy: Copy | None = None, **options):
    L.seed_everything(0)
    seen: list = []
    net = Net(augment, seen)
    save = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "run", monitor="val", save_last=True)
    trainer = L.Trainer(
        max_epochs=epochs,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[save, GlobalGenerators(), *([copy] if copy else [])],
        **options,
    )
    trainer.fit(net, ckpt_path=ckpt)
    return seen, [p.detach().clone() for p in net.parameters()]


def test_the_order_is_what_a_shuffling_loader_with_that_generator_gives():
    ours = ResumableLoader(list(range(10)), 3, torch.Generator().manual_seed(7))
    theirs = DataLoader(list(range(10)), 3, shuffle=True, generator=torch.Generator().manual_seed(7))
    for _ in range(3):  # epochs
        assert [b.tolist() for b in ours] == [b.tolist() for b in theirs]


def test_a_job_resumed_after_an_epoch_trains_as_the_uninterrupted_job(tmp_path):
    seen, weights = fit(tmp_path, augment=True, epochs=3, copy=Copy(None, 0, tmp_path / "epoch0.ckpt"))
    assert len({tuple(b) for e, b in seen if e == 0} ^ {tuple(b) for e, b in seen if e == 1}) > 0  # orders differ
    resumed_seen, resumed = fit(tmp_path, augment=True, epochs=3, ckpt=tmp_path / "epoch0.ckpt")
    assert resumed_seen == [s for s in seen if s[0] > 0]
    assert all(torch.equal(a, b) for a, b in zip(weights, resumed))


def test_a_job_stopped_mid_epoch_resumes_at_the_next_batch(tmp_path):
    seen, weights = fit(tmp_path, augment=False, epochs=3, copy=Copy((1, 1), None, tmp_path / "stop.ckpt"))
    resumed_seen, resumed = fit(tmp_path, augment=False, epochs=3, ckpt=tmp_path / "stop.ckpt")
    assert resumed_seen == seen[len(seen) - len(resumed_seen) :] and resumed_seen[0] == seen[6]  # epoch 1, batch 2
    assert all(torch.equal(a, b) for a, b in zip(weights, resumed))


def test_an_epoch_cut_short_by_limit_train_batches_resumes_at_the_next_epoch(tmp_path):
    seen, weights = fit(tmp_path, True, 3, copy=Copy(None, 0, tmp_path / "epoch0.ckpt"), limit_train_batches=2)
    resumed_seen, resumed = fit(tmp_path, True, 3, ckpt=tmp_path / "epoch0.ckpt", limit_train_batches=2)
    assert resumed_seen == [s for s in seen if s[0] > 0] and len(resumed_seen) == 4
    assert all(torch.equal(a, b) for a, b in zip(weights, resumed))
