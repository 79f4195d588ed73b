"""Camera/LiDAR complementarity of a KITTI-layout dataset, from the data alone (no model): for every labelled
object, does the LiDAR return from it, and does it stand out in the camera image, under each camera condition?

``python -m ablate.data stats --root DIR --out results/NAME [--frames N]`` writes NAME.md and NAME.png.

- **Objects**: Car and Pedestrian (DontCare and the other classes are skipped) at least 25 px tall at KITTI's
  375-row scale (:func:`ablate.data.difficulty.counted`, the rule the AP counts by). Distance: the horizontal range
  ``hypot(x, z)`` of the box's bottom centre from the camera.
- **LiDAR hit**: at least ``MIN_RETURNS`` velodyne returns inside the object's 3D box (velodyne -> rectified camera
  frame through ``Tr_velo_to_cam`` and ``R0_rect``), the box enlarged by ``MARGIN`` on its four sides and at its top
  and its bottom raised by ``GROUND``, so that label noise loses no return and the road under it counts none.
- **Camera visible**: the CIE 1976 colour difference ΔE*ab between the mean CIELab colour of the object's pixels
  (its mask in instance_2/ where present, else its 2D box with ``SHRINK`` of each side cut off, which leaves out
  most of the background in the box's corners) and the mean colour of a ring around its 2D box (``RING`` x the box's
  shorter side wide, at least 2 px), at least ``JND + NOISE_K * sigma``: ``JND`` = 2.3 is the just-noticeable
  difference of ΔE*ab (Sharma & Trussell 1997), ``sigma`` the image's per-pixel noise in L* after the condition
  (Immerkær 1996's estimator), so a difference that the pixel noise could make does not count as visible.
- **Conditions**: every frame's image goes through each of :data:`ablate.data.conditions.CONDITIONS` with the rng the
  dataset gives that frame (``default_rng([seed, crc32(frame)])``), so the rows compare the same objects under the
  same drops, wipers and glare spots. The LiDAR side does not depend on the condition.
- **Height of the objects the LiDAR misses** (:func:`missed_heights`): their 2D box height in pixels, rescaled from
  the data's own rows to each of ``HEIGHT_ROWS`` rows (the image heights a scale could train at; 375 is KITTI's),
  and the share at least ``MIN_PX`` tall. These are the objects only the camera can add (SMoE's "RGB only"), so
  the camera expert must be able to find them at the scale's resolution. ``MIN_PX`` = 20 is the resolution
  target of the issue on SMoE's data (about 2.5 cells of P3, stride 8, the finest level the instance head
  predicts from); a reading of that target, not a figure from the paper.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from tqdm import tqdm  # noqa: E402

from ablate.config import RESULTS  # noqa: E402
from ablate.data import DataError, kitti  # noqa: E402
from ablate.data.conditions import CONDITIONS, apply_condition  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.figure import Figure

CLASSES = ("Car", "Pedestrian")
MIN_RETURNS, MARGIN, GROUND = 10, 0.2, 0.1  # returns; metres; metres
JND, NOISE_K = 2.3, 3.0  # ΔE*ab; multiples of the per-pixel L* noise
SHRINK, RING = 0.15, 0.25  # fractions of the 2D box
HEIGHT_ROWS, MIN_PX = (128, 192, 256, 320, 375), 20.0  # image rows; pixels
BINS, BIN_LABELS = (0.0, 15.0, 30.0, 45.0, np.inf), ("0-15 m", "15-30 m", "30-45 m", "45+ m")
PATTERNS = ("both", "LiDAR only", "camera only", "neither")
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def returns_in_box(points: np.ndarray, obj: kitti.Object3D, margin: float = MARGIN, ground: float = GROUND) -> int:
    """How many of ``points`` ((N,3), rectified camera frame) lie in ``obj``'s 3D box enlarged by ``margin`` metres
    on its four sides and at its top, with its bottom raised by ``ground`` metres (:meth:`Object3D.contains`)."""
    return int(obj.contains(points, margin, ground).sum())


def noise_sigma(channel: np.ndarray) -> float:
    """Per-pixel noise standard deviation of an (H,W) image (J. Immerkær, "Fast noise variance estimation", 1996)."""
    h, w = channel.shape
    lap = cv2.filter2D(np.asarray(channel, np.float32), -1, _IMMERKAER)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) * np.abs(lap).sum() / (6 * (w - 2) * (h - 2)))


def contrast(
    lab: np.ndarray,
    bbox: tuple[float, float, float, float],
    mask: np.ndarray | None = None,
    shrink: float = SHRINK,
    ring: float = RING,
) -> float:
    """ΔE*ab between the mean colour of an object in ``lab`` ((H,W,3) CIELab) and of a ring around its 2D box
    ``bbox`` (xyxy px). The object's pixels are ``mask`` ((H,W) bool) where given and not empty, else ``bbox`` with
    ``shrink`` of each side cut off; the ring is ``ring`` x the box's shorter side wide (at least 2 px). NaN when the
    ring lies outside the image."""
    h, w = lab.shape[:2]
    x0, y0, x1, y1 = bbox
    bw, bh = x1 - x0, y1 - y0
    r = max(2.0, ring * min(bw, bh))
    top, left = max(0, int(np.floor(y0 - r))), max(0, int(np.floor(x0 - r)))
    yy, xx = np.mgrid[top : min(h, int(np.ceil(y1 + r)) + 1), left : min(w, int(np.ceil(x1 + r)) + 1)]
    crop = lab[top : top + yy.shape[0], left : left + yy.shape[1]]
    within = lambda a, b, c, d: (xx >= a) & (xx <= c) & (yy >= b) & (yy <= d)  # noqa: E731
    around = within(x0 - r, y0 - r, x1 + r, y1 + r) & ~within(x0, y0, x1, y1)
    obj = None if mask is None else mask[top : top + yy.shape[0], left : left + yy.shape[1]]
    if obj is None or not obj.any():
        obj = within(x0 + shrink * bw, y0 + shrink * bh, x1 - shrink * bw, y1 - shrink * bh)
    if not obj.any() or not around.any():
        return float("nan")
    return float(np.linalg.norm(crop[obj].mean(0) - crop[around].mean(0)))


def frame_objects(
    split_dir: Path, frame: str, conditions: Sequence[str] = tuple(CONDITIONS), seed: int = 0, severity: float = 1.0
) -> list[dict]:
    """One record per counted object of ``frame`` and condition: class, distance, height (px) and the image's rows,
    returns, ΔE, threshold."""
    from ablate.data.difficulty import counted

    paths = kitti.frame_paths(split_dir, frame)
    image = kitti.read_image(paths["image"]).astype(np.float32) / 255.0
    labels = kitti.read_labels(paths["label"])
    keep = [k for k, o in enumerate(labels) if o.type in CLASSES]
    heights = np.array([labels[k].bbox[3] - labels[k].bbox[1] for k in keep])
    keep = [k for k, ok in zip(keep, counted(heights, image.shape[0])) if ok]
    if not keep:
        return []
    points = kitti.Calibration.from_file(paths["calib"]).velo_to_rect(kitti.read_velodyne(paths["velodyne"]))
    inst = cv2.imread(str(paths["instance"]), cv2.IMREAD_UNCHANGED) if paths["instance"].is_file() else None
    objects = [labels[k] for k in keep]
    base = [
        {
            "frame": frame,
            "object": k,
            "class": o.type,
            "distance": float(np.hypot(o.location[0], o.location[2])),
            "height": o.bbox[3] - o.bbox[1],
            "rows": image.shape[0],
            "returns": returns_in_box(points, o),
        }
        for k, o in zip(keep, objects)
    ]
    masks = [None if inst is None else inst == k + 1 for k in keep]
    rows = []
    for name in conditions:
        rng = np.random.default_rng([seed, zlib.crc32(frame.encode())])
        lab = cv2.cvtColor(apply_condition(name, image, rng, severity), cv2.COLOR_RGB2Lab)
        threshold = JND + NOISE_K * noise_sigma(lab[..., 0])
        rows += [
            {**b, "condition": name, "delta_e": contrast(lab, o.bbox, m), "threshold": threshold}
            for o, b, m in zip(objects, base, masks)
        ]
    return rows


def compute(
    root: str | Path,
    frames: int | None = None,
    conditions: Sequence[str] = tuple(CONDITIONS),
    seed: int = 0,
    severity: float = 1.0,
    min_returns: int = MIN_RETURNS,
    progress: bool = True,
) -> pd.DataFrame:
    """One row per counted object and condition of the first ``frames`` frames under ``root`` (all if None), with
    booleans ``lidar`` (LiDAR hit) and ``camera`` (camera visible) and the distance bin."""
    from ablate.data.datamodule import resolve_split_dir

    split_dir = resolve_split_dir(root)
    for sub, what in (("label_2", "labels"), ("velodyne", "LiDAR scans")):
        if not (split_dir / sub).is_dir():
            raise DataError(f"{split_dir}: no {sub}/ ({what}); the complementarity report needs labels and LiDAR")
    names = kitti.list_frames(split_dir)[:frames]
    rows = [
        r
        for f in tqdm(names, desc=f"stats {root}", unit="frame", disable=(not progress) or None)
        for r in frame_objects(split_dir, f, conditions, seed, severity)
    ]
    if not rows:
        raise DataError(
            f"{split_dir}: no {' or '.join(CLASSES)} at least 25 px tall (at 375 rows) in {len(names)} frame(s)"
        )
    df = pd.DataFrame(rows)
    df["lidar"] = df["returns"] >= min_returns
    df["camera"] = df["delta_e"] >= df["threshold"]  # NaN (no ring in the image) is not visible
    df["bin"] = pd.cut(df["distance"], BINS, right=False, labels=BIN_LABELS)
    df["class"] = pd.Categorical(df["class"], [c for c in CLASSES if c in set(df["class"])])
    df["condition"] = pd.Categorical(df["condition"], list(conditions))
    return df


def summarize(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Per group of ``by``: distinct objects, the share (%) of object-condition pairs LiDAR-hit, camera-visible and
    in each of :data:`PATTERNS`, and the median returns per object."""
    lidar, camera = df["lidar"].astype(bool), df["camera"].astype(bool)
    flags = pd.DataFrame(
        {
            "LiDAR hit": lidar,
            "camera visible": camera,
            "both": lidar & camera,
            "LiDAR only": lidar & ~camera,
            "camera only": ~lidar & camera,
            "neither": ~lidar & ~camera,
        }
    )
    groups = [df[k] for k in by]
    out = (flags.astype(float) * 100).groupby(groups, observed=True).mean().add_suffix(" %")
    out.insert(
        0,
        "objects",
        (df["frame"].astype(str) + "/" + df["object"].astype(str)).groupby(groups, observed=True).nunique(),
    )
    out["median returns"] = df["returns"].groupby(groups, observed=True).median()
    return out.reset_index()


def missed_heights(df: pd.DataFrame, rows: Sequence[int] = HEIGHT_ROWS, min_px: float = MIN_PX) -> pd.DataFrame:
    """Per image height in ``rows``: the objects the LiDAR misses (``lidar`` false; each object once), the
    quartiles of their 2D box height rescaled from the data's own rows (``height * r / rows``), and the share (%)
    at least ``min_px`` tall."""
    one = df.drop_duplicates(["frame", "object"])
    missed = one[~one["lidar"].astype(bool)]
    out = []
    for r in rows:
        px = (missed["height"] * r / missed["rows"]).to_numpy(float)
        q = np.percentile(px, [25, 50, 75]) if len(px) else [np.nan] * 3
        out.append(
            {
                "image rows": r,
                "objects": len(px),
                "25th pct (px)": q[0],
                "median (px)": q[1],
                "75th pct (px)": q[2],
                f"≥ {min_px:g} px %": 100 * float(np.mean(px >= min_px)) if len(px) else np.nan,
            }
        )
    return pd.DataFrame(out)


def with_all(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` plus a copy of it under condition "all" (every object once per condition)."""
    order = [*df["condition"].cat.categories, "all"]
    pooled = pd.concat([df.assign(condition=df["condition"].astype(str)), df.assign(condition="all")])
    return pooled.assign(condition=pd.Categorical(pooled["condition"], order))


def to_markdown(df: pd.DataFrame, root: str, command: str, min_returns: int = MIN_RETURNS) -> str:
    one = df.drop_duplicates(["frame", "object"])
    conditions = ", ".join(df["condition"].cat.categories)

    def table(by: list[str]) -> str:
        return summarize(with_all(df), by).rename(columns={"bin": "distance"}).to_markdown(index=False, floatfmt=".1f")

    lines = [
        f"# Camera/LiDAR complementarity of `{root}`",
        "",
        f"{len(one)} objects ({', '.join(f'{n} {c}' for c, n in one['class'].value_counts(sort=False).items())})"
        f" in {df['frame'].nunique()} frame(s) with one, counted as the AP counts them: Car and Pedestrian at "
        "least 25 px tall at KITTI's 375-row scale. Computed from the data alone, with no model.",
        "",
        f"- **LiDAR hit**: at least {min_returns} LiDAR returns inside the object's 3D box, the box enlarged by "
        f"{MARGIN} m on its four sides and at its top and its bottom raised by {GROUND} m (the road under it "
        "counts no return). *Median returns*: per object.",
        f"- **Camera visible**: colour difference ΔE*ab (CIELab, CIE 1976) between the mean colour of the "
        f"object (its instance mask where the data has one, else its 2D box less {SHRINK:.0%} of each side) and "
        f"of a ring around its 2D box ({RING:.0%} of its shorter side wide, at least 2 px) at least "
        f"{JND} + {NOISE_K:g} σ: {JND} is the just-noticeable difference of ΔE*ab, σ the image's per-pixel "
        "noise in L* after the condition (Immerkær's estimator), so a difference the pixel noise could make "
        f"does not count. Median threshold here: {df['threshold'].median():.1f}.",
        f"- **Conditions** ({conditions}): the camera side is evaluated on every frame under each condition, with "
        "the rng the dataset gives that frame, so the rows compare the same objects; the LiDAR side does not "
        "change with the condition. *all*: every object once per condition; shares (%) are of "
        "object-condition pairs.",
        "",
        "## Per condition",
        "",
        table(["condition"]),
        "",
        "## Per distance bin",
        "",
        "Distance: horizontal range of the box's bottom centre from the camera.",
        "",
        table(["condition", "bin"]),
        "",
        "## Per class",
        "",
        table(["condition", "class"]),
        "",
        "## Height of the objects the LiDAR misses",
        "",
        f"The objects with fewer than {min_returns} returns (each once), their 2D box height rescaled from the "
        f"data's {'/'.join(str(r) for r in sorted(set(df['rows'])))} rows to each image height: the objects only "
        f"the camera can add, and how tall the camera sees them at that resolution. {MIN_PX:g} px: the "
        "resolution target for the instance task's camera expert (about 2.5 cells of P3, stride 8).",
        "",
        missed_heights(df).to_markdown(index=False, floatfmt=(".0f", ".0f", ".1f", ".1f", ".1f", ".1f")),
        "",
        f"Regenerated by `{command}`; do not edit by hand.",
        "",
    ]
    return "\n".join(lines)


def plot(df: pd.DataFrame, min_returns: int = MIN_RETURNS) -> Figure:
    """Shares of the four patterns per condition; LiDAR-hit and camera-visible shares per distance bin; returns
    against distance."""
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    per = summarize(df, ["condition"])
    bottom = np.zeros(len(per))
    for pattern, colour in zip(PATTERNS, ("C2", "C0", "C1", "0.6")):
        axes[0].bar(per["condition"].astype(str), per[f"{pattern} %"], bottom=bottom, color=colour, label=pattern)
        bottom += per[f"{pattern} %"].to_numpy()
    axes[0].set_ylabel("% of objects")
    axes[0].legend(fontsize=8, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.08))
    axes[0].set_title("Seen by LiDAR (hit) and camera (visible), per condition", fontsize=9)
    bins = summarize(df, ["condition", "bin"])
    lidar = summarize(df[df["condition"] == df["condition"].cat.categories[0]], ["bin"])
    x = np.arange(len(lidar))
    axes[1].plot(x, lidar["LiDAR hit %"], "k-o", lw=2.5, label="LiDAR hit")
    groups = list(bins.groupby("condition", observed=True))
    for k, (cond, g) in enumerate(groups):  # dodged sideways so that equal shares stay apart
        axes[1].plot(
            x + 0.04 * (k + 1 - (len(groups) + 1) / 2) * 2,
            g["camera visible %"],
            "--o",
            ms=4,
            color=f"C{3 + k}",
            label=f"camera visible: {cond}",
        )
    axes[1].set_xticks(x, [f"{b}\n{n} objects" for b, n in zip(lidar["bin"], lidar["objects"])])
    axes[1].set_ylim(-3, 103)
    axes[1].set_ylabel("% of objects")
    axes[1].legend(fontsize=7)
    axes[1].set_title("Per distance bin", fontsize=9)
    one = df.drop_duplicates(["frame", "object"])
    for k, (cls, g) in enumerate(one.groupby("class", observed=True)):
        axes[2].scatter(g["distance"], g["returns"], s=12, alpha=0.7, color=f"C{k}", label=str(cls))
    axes[2].axhline(min_returns, color="k", lw=0.8, ls="--", label=f"{min_returns} returns")
    axes[2].set_yscale("symlog", linthresh=1)
    axes[2].set_ylim(0, max(2 * one["returns"].max(), 10 * min_returns))
    axes[2].set_xlabel("distance (m)")
    axes[2].set_ylabel("LiDAR returns in the box")
    axes[2].legend(fontsize=7)
    axes[2].set_title("Returns per object against distance", fontsize=9)
    fig.tight_layout()
    return fig


def report(
    root: str | Path, out: str | Path = RESULTS / "complementarity", frames: int | None = None, progress: bool = True
) -> tuple[Path, Path]:
    """Write ``out``.md and ``out``.png for the dataset under ``root``; return their paths."""
    df = compute(root, frames, progress=progress)
    out = Path(out)
    out = out.with_suffix("") if out.suffix in (".md", ".png") else out
    out.parent.mkdir(parents=True, exist_ok=True)
    md, png = out.parent / f"{out.name}.md", out.parent / f"{out.name}.png"
    command = f"python -m ablate.data stats --root {root} --out {out}" + (f" --frames {frames}" if frames else "")
    md.write_text(to_markdown(df, str(root), command))
    fig = plot(df)
    fig.savefig(png, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return md, png
