"""How many weight updates the cpu-scale SSD needs: train a detection row on a few training frames and test it on
those same frames (memorising them is the easiest thing a detector can do), at several update counts.

    PYTHONPATH=. python bench/bench_detection_capacity.py [--row ssd_dhi] [--frames 16] [--steps 100,300]
        [--set model.batch_norm=true ...]

Prints per step count: wall seconds, seconds per update, the final training loss and KITTI AP (11-point, Car
moderate, and the moderate mean over Car and Pedestrian) on the memorised frames. Runs on the generated default
data in ./data (made first if missing), with the row's cpu recipe (Adam, lr 0.001, poly decay over the run).

On this 2-core machine, with one thread while another training job held the other core (2026-11-24): ssd_dhi on
16 frames, 300 updates at batch 8, 278 s (0.93 s per update), loss 0.83, Car moderate 47.1 %, mean 29.5 % on the
memorised frames. dgfn_table1's cpu recipe gives DGFN 226 updates over 900 frames, which left it at Car moderate
0.4 % on the test frames: at this scale the SSD needs several times more updates than the cpu budget holds.
With ``--set model.batch_norm=true`` (ScratchDet's BatchNorm in the trunk, ablate.nn.vgg), same machine and load:
300 updates 477 s (1.59 s per update), loss 0.03, Car moderate 63.6 %, mean 45.5 %: the cpu recipe now has it
(conf/recipe/detection_cpu.yaml; docs/recipes.md#detection_cpu).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

REPO = Path(__file__).resolve().parents[1]


def measure(row: str, frames: int, steps: int, seed: int, overrides: list[str] = ()) -> dict[str, float]:
    import ablate  # noqa: F401  (registers the config resolvers)

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                f"row={row}",
                "task=detection",
                f"seed={seed}",
                f"+data.limit_frames={{train:{frames},val:{frames},test:{frames}}}",
                *overrides,
            ],
        )
    L.seed_everything(seed, workers=True)
    data = instantiate(cfg.data)
    data.prepare_data()
    data.setup("fit")
    data.val_dataloader = data.train_dataloader
    data.test_dataloader = lambda: data._loader("train", False)  # the memorised frames, in order
    task = instantiate(cfg.task, model=instantiate(cfg.model))
    trainer = L.Trainer(
        max_steps=steps,
        max_epochs=-1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
    )
    start = time.perf_counter()
    trainer.fit(task, datamodule=data)
    wall = time.perf_counter() - start
    loss = float(trainer.logged_metrics.get("train/loss", float("nan")))
    test = trainer.test(task, datamodule=data, verbose=False)[0]
    return {
        "wall_s": wall,
        "s_per_update": wall / steps,
        "loss": loss,
        "car_moderate": float(test["test/car_moderate"]),
        "ap11": float(test["test/ap11"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--row", default="ssd_dhi")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--steps", default="100,300")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override")
    args = parser.parse_args()
    os.chdir(REPO)
    print(
        f"row {args.row} {' '.join(args.set)}, {args.frames} frames, {torch.get_num_threads()} thread(s), "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    print("updates  wall s  s/update  loss   Car moderate %  AP moderate %")
    for steps in (int(s) for s in args.steps.split(",")):
        r = measure(args.row, args.frames, steps, args.seed, args.set)
        print(
            f"{steps:7d}  {r['wall_s']:6.0f}  {r['s_per_update']:8.2f}  {r['loss']:5.2f}  "
            f"{r['car_moderate']:14.1f}  {r['ap11']:13.1f}"
        )


if __name__ == "__main__":
    main()
