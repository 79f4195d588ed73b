"""Training throughput of the framework (Lightning Trainer + SemanticTask + MLflow logger) against a bare PyTorch
loop with the same model, data and optimiser. Target: framework >= 0.97 of bare.

    python bench/bench_loop_throughput.py [--steps 60] [--repeats 3]

Both loops read the same pre-loaded batches (data loading is measured by bench_data*.py), so the ratio isolates
what the framework adds per step: Lightning's loop, logging, the progress bar and the NaN check. Both are timed
from the first step's start to the last step's end (the Trainer's one-time set-up is not a per-step cost).
"""

from __future__ import annotations

import argparse
import functools
import statistics
import tempfile
import time
import warnings

import lightning as L
import torch

from ablate.nn.chinet import build
from ablate.store import RunLogger, Tracker
from ablate.tasks.semantic import SemanticTask

warnings.filterwarnings("ignore")


def make_batches(n: int, batch: int, h: int, w: int) -> list[dict]:
    g = torch.Generator().manual_seed(0)
    out = []
    for _ in range(n):
        sem = torch.randint(0, 3, (batch, h, w), generator=g)
        out.append(
            {
                "intensity": torch.rand(batch, 1, h, w, generator=g),
                "dense_depth": torch.rand(batch, 1, h, w, generator=g),
                "semantic": sem,
                "free_space": (sem == 1).float()[:, None],
                "road_objects": (sem == 2).float()[:, None],
            }
        )
    return out


def new_task() -> SemanticTask:
    torch.manual_seed(0)
    model = build("chinet", {"intensity": 1, "dense_depth": 1}, [16, 32, 64, 128])
    return SemanticTask(model, functools.partial(torch.optim.Adam, lr=1e-3))


def bare(batches: list[dict]) -> float:
    task = new_task()
    opt = task.configure_optimizers()
    task.train()
    start = time.perf_counter()
    for batch in batches:
        opt.zero_grad(set_to_none=True)
        loss = task.loss(task.model(batch), batch)
        loss.backward()
        opt.step()
    return len(batches) / (time.perf_counter() - start)


class StepClock(L.Callback):
    """Times the training steps themselves: from the first batch's start to the last batch's end."""

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        if batch_idx == 0:
            self.start = time.perf_counter()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.end = time.perf_counter()


def framework(batches: list[dict], tracker: Tracker) -> float:
    task = new_task()
    clock = StepClock()
    run = tracker.start(tracker.experiment_id("bench"), "bench", {})
    trainer = L.Trainer(
        max_epochs=1,
        logger=RunLogger(tracker, run),
        enable_checkpointing=False,
        enable_model_summary=False,
        log_every_n_steps=5,
        num_sanity_val_steps=0,
        enable_progress_bar=True,
        accelerator="cpu",
        callbacks=[clock],
    )
    loader = torch.utils.data.DataLoader(batches, batch_size=None, shuffle=False)
    trainer.fit(task, train_dataloaders=loader)
    return len(batches) / (clock.end - clock.start)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--batch", type=int, default=8)
    args = p.parse_args()
    batches = make_batches(args.steps, args.batch, 128, 416)
    with tempfile.TemporaryDirectory() as tmp:
        tracker = Tracker(f"sqlite:///{tmp}/mlflow.db", f"{tmp}/artifacts")
        bare(batches[:5])  # warm-up
        results = {"bare": [], "framework": []}
        for _ in range(args.repeats):
            results["bare"].append(bare(batches))
            results["framework"].append(framework(batches, tracker))
    b, f = statistics.median(results["bare"]), statistics.median(results["framework"])
    print(
        f"\nthreads={torch.get_num_threads()} steps={args.steps} batch={args.batch} input=128x416 model=ChiNet[16..128]"
    )
    print(f"bare PyTorch loop : {b:7.2f} steps/s  (runs: {', '.join(f'{x:.2f}' for x in results['bare'])})")
    print(f"framework         : {f:7.2f} steps/s  (runs: {', '.join(f'{x:.2f}' for x in results['framework'])})")
    print(f"ratio framework/bare: {f / b:.3f}  (target >= 0.97)")


if __name__ == "__main__":
    main()
