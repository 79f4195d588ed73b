"""Generated dataset and cache figures: generator frames/s, default dataset time and size, cost of one sample
with a cold and a warm cache, and of one BiFNet training sample with and without augmentation. Usage: python bench/bench_data.py [OUT_DIR]."""

from __future__ import annotations

import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from ablate.data.datamodule import DEFAULT_SYNTH, KittiDataModule, ensure_synth
from ablate.data.generate import generate, render_frame


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="bench_data_"))
    t = time.perf_counter()
    for i in range(20):
        render_frame(0, i, 128, 416)
    print(f"render only, 128x416, 1 process: {20 / (time.perf_counter() - t):.1f} frames/s")
    t = time.perf_counter()
    generate(out / "smoke", 24, 0, 64, 208, progress=False)
    print(f"smoke dataset, 24 frames 64x208, 1 process: {time.perf_counter() - t:.2f} s")
    t = time.perf_counter()
    root = ensure_synth(out, None)
    dt = time.perf_counter() - t
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    print(
        f"default dataset {DEFAULT_SYNTH}: {dt:.1f} s, {DEFAULT_SYNTH['frames'] / dt:.1f} frames/s, {size / 1e6:.0f} MB"
    )
    mods = ["rgb", "intensity", "sparse_depth", "dense_depth", "ddm_jet", "dhi", "bev"]
    dm = KittiDataModule(
        data_dir=str(out), modalities=mods, targets=["semantic", "instances", "boxes2d"], conditions=["night"]
    )
    dm.setup()
    ds = dm.datasets["train"]
    n = 50
    t = time.perf_counter()
    for i in range(n):
        ds[i]
    cold = (time.perf_counter() - t) / n
    t = time.perf_counter()
    for i in range(n):
        ds[i]
    warm = (time.perf_counter() - t) / n
    print(
        f"one sample (all modalities, night, semantic+instances+boxes2d): cold cache {cold * 1e3:.1f} ms, "
        f"cached {warm * 1e3:.1f} ms"
    )
    road(out)
    if len(sys.argv) <= 1:
        shutil.rmtree(out)


def road(out: Path, n: int = 50, rounds: int = 3) -> None:
    """One BiFNet training sample (rgb, bev, road targets, DST / SHPL geometry) with a warm cache, plain and with
    the paper-scale augmentation (ablate.data.augment; its flipped views cached by a first pass). The two are timed
    interleaved, sample by sample, and the median is printed, so load on the machine hits both alike."""
    targets = [
        "free_space",
        "road_valid",
        "road_bev",
        "road_bev_valid",
        "calib",
        "height_image",
        "height_bev",
        "lidar_points",
    ]
    sets = {}
    for name, augment in (("plain", None), ("augmented", {"flip": 0.5, "scale": [1.0, 1.2]})):
        dm = KittiDataModule(
            data_dir=str(out),
            modalities=["rgb", "bev"],
            targets=targets,
            augment=augment,
            bev={
                "x_range": [6.0, 46.0],
                "y_range": [-10.0, 10.0],
                "cell": 0.5,
                "window": 4,
                "azimuth_res": 0.2,
                "max_points": 16384,
            },
        )
        dm.setup()
        sets[name] = dm.datasets["train"]
        for _ in range(4 if augment else 1):  # fill the cache (both views of a flipped frame)
            for i in range(n):
                sets[name][i]
    times = {name: [] for name in sets}
    for _ in range(rounds):
        for i in range(n):
            for name, ds in sets.items():
                t = time.perf_counter()
                ds[i]
                times[name].append(time.perf_counter() - t)
    med = {name: statistics.median(ts) * 1e3 for name, ts in times.items()}
    print(
        f"one BiFNet training sample (rgb, bev, road targets, geometry), cached, median of {rounds * n}: "
        f"{med['plain']:.1f} ms plain, {med['augmented']:.1f} ms with flip 0.5 and zoom 1.0-1.2"
    )


if __name__ == "__main__":
    main()
