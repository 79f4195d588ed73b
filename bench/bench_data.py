"""Generated dataset and cache figures: generator frames/s, default dataset time and size, cost of one sample
with a cold and a warm cache. Usage: python bench/bench_data.py [OUT_DIR]."""
from __future__ import annotations

import shutil
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
    print(f"default dataset {DEFAULT_SYNTH}: {dt:.1f} s, {DEFAULT_SYNTH['frames'] / dt:.1f} frames/s, "
          f"{size / 1e6:.0f} MB")
    mods = ["rgb", "intensity", "sparse_depth", "dense_depth", "ddm_jet", "dhi", "bev"]
    dm = KittiDataModule(data_dir=str(out), modalities=mods, targets=["semantic", "instances", "boxes2d"],
                         conditions=["night"])
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
    print(f"one sample (all modalities, night, semantic+instances+boxes2d): cold cache {cold * 1e3:.1f} ms, "
          f"cached {warm * 1e3:.1f} ms")
    if len(sys.argv) <= 1:
        shutil.rmtree(out)


if __name__ == "__main__":
    main()
