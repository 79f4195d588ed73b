"""Complementarity report: returns in a box, colour contrast, the summary's arithmetic, the CLI end to end."""

import cv2
import numpy as np
import pandas as pd
import pytest

from ablate.data.__main__ import main
from ablate.data.kitti import Calibration, Object3D
from ablate.data.stats import (
    GROUND,
    MARGIN,
    compute,
    contrast,
    missed_heights,
    noise_sigma,
    returns_in_box,
    summarize,
    with_all,
)

CAR = Object3D("Car", 0.0, 0, 0.0, (0, 0, 0, 0), (1.5, 1.6, 4.0), (2.0, 1.7, 20.0), 0.3)


def _to_rect(obj: Object3D, local: np.ndarray) -> np.ndarray:
    """Box-frame points (along the length, height above the bottom, along the width) -> rectified camera frame."""
    c, s = np.cos(obj.rotation_y), np.sin(obj.rotation_y)
    x, up, z = local.T
    return np.stack([c * x + s * z, -up, -s * x + c * z], 1) + np.asarray(obj.location)


def _uniform(rng, n, lo, hi):
    return rng.uniform(lo, hi, (n, 3))


def test_returns_in_box_counts_the_enlarged_box_above_the_road():
    rng = np.random.default_rng(0)
    h, w, l = CAR.dimensions
    inside = _uniform(rng, 37, (-l / 2, GROUND + 0.01, -w / 2), (l / 2, h, w / 2))
    margin = np.array([[l / 2 + MARGIN / 2, 0.8, 0.0], [0.0, h + MARGIN / 2, 0.0], [0.0, 0.8, -w / 2 - MARGIN / 2]])
    road = _uniform(rng, 11, (-l / 2, 0.0, -w / 2), (l / 2, GROUND - 0.01, w / 2))
    outside = np.array(
        [
            [l / 2 + MARGIN + 0.05, 0.8, 0.0],
            [0.0, h + MARGIN + 0.05, 0.0],
            [0.0, -0.05, 0.0],
            [0.0, 0.8, w / 2 + MARGIN + 0.05],
        ]
    )
    points = _to_rect(CAR, np.vstack([inside, margin, road, outside]))
    assert returns_in_box(points, CAR) == 37 + 3
    assert returns_in_box(points, CAR, margin=0.0, ground=0.0) == 37 + 11
    assert returns_in_box(points[:0], CAR) == 0


def _lab(rgb) -> np.ndarray:
    return cv2.cvtColor(np.array([[rgb]], np.float32), cv2.COLOR_RGB2Lab)[0, 0]


def test_contrast_is_the_lab_distance_between_the_object_and_its_ring():
    grey, red = (0.5, 0.5, 0.5), (0.7, 0.2, 0.2)
    img = np.full((100, 200, 3), grey, np.float32)
    img[30:71, 60:121] = red
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2Lab)
    expected = np.linalg.norm(_lab(red) - _lab(grey))
    assert contrast(lab, (60, 30, 120, 70)) == pytest.approx(expected, rel=1e-4)
    # a stripe in a grey box: the mask sees the stripe's full contrast, the box proxy a diluted one
    img = np.full((100, 200, 3), grey, np.float32)
    img[45:56, 60:121] = red
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2Lab)
    mask = np.zeros((100, 200), bool)
    mask[45:56, 60:121] = True
    assert contrast(lab, (60, 30, 120, 70), mask) == pytest.approx(expected, rel=1e-4)
    assert 0 < contrast(lab, (60, 30, 120, 70)) < 0.5 * expected
    assert contrast(lab, (60, 30, 120, 70), np.zeros_like(mask)) == contrast(lab, (60, 30, 120, 70))  # empty mask
    assert np.isnan(contrast(lab, (0, 0, 199, 99)))  # no ring inside the image


def test_noise_sigma_estimates_the_pixel_noise():
    rng = np.random.default_rng(1)
    flat = 50 + rng.normal(0, 2.0, (200, 300))
    assert noise_sigma(flat) == pytest.approx(2.0, rel=0.05)
    assert noise_sigma(np.full((50, 50), 50.0)) == 0.0


def test_summary_shares_and_medians():
    # 4 objects x 2 conditions: LiDAR hits objects 0 and 1; the camera sees 0 and 2 in clear, only 2 at night.
    df = pd.DataFrame(
        {
            "frame": ["a", "a", "b", "b"] * 2,
            "object": [0, 1, 0, 1] * 2,
            "class": ["Car", "Car", "Car", "Pedestrian"] * 2,
            "returns": [50, 12, 3, 0] * 2,
            "lidar": [True, True, False, False] * 2,
            "camera": [True, False, True, False, False, False, True, False],
            "condition": pd.Categorical(["clear"] * 4 + ["night"] * 4, ["clear", "night"]),
        }
    )
    s = summarize(df, ["condition"]).set_index("condition")
    assert list(s["objects"]) == [4, 4]
    assert list(s["LiDAR hit %"]) == [50, 50] and list(s["camera visible %"]) == [50, 25]
    assert s.loc["clear", ["both %", "LiDAR only %", "camera only %", "neither %"]].tolist() == [25, 25, 25, 25]
    assert s.loc["night", ["both %", "LiDAR only %", "camera only %", "neither %"]].tolist() == [0, 50, 25, 25]
    assert list(s["median returns"]) == [7.5, 7.5]
    pooled = summarize(with_all(df), ["condition"]).set_index("condition")
    assert list(pooled.index) == ["clear", "night", "all"]
    assert pooled.loc["all", "objects"] == 4 and pooled.loc["all", "camera visible %"] == 37.5
    assert pooled.loc["all", "median returns"] == 7.5
    per_class = summarize(df, ["class"]).set_index("class")
    assert per_class.loc["Pedestrian", "objects"] == 1 and per_class.loc["Pedestrian", "neither %"] == 100


def test_missed_heights_rescale_the_objects_the_lidar_misses():
    # 128-row data, 2 conditions: the LiDAR misses the 8 and 12 px objects (each counted once), hits the 30 px one
    df = pd.DataFrame(
        {
            "frame": ["a", "a", "b"] * 2,
            "object": [0, 1, 0] * 2,
            "height": [8.0, 12.0, 30.0] * 2,
            "rows": [128] * 6,
            "lidar": [False, False, True] * 2,
        }
    )
    out = missed_heights(df, rows=(128, 256, 375), min_px=20).set_index("image rows")
    assert list(out["objects"]) == [2, 2, 2]
    assert out["median (px)"].tolist() == pytest.approx([10.0, 20.0, 10.0 * 375 / 128])
    assert out["25th pct (px)"].tolist() == pytest.approx([9.0, 18.0, 9.0 * 375 / 128])
    assert out["≥ 20 px %"].tolist() == [0.0, 50.0, 100.0]  # 24 px at 256 rows counts, 16 does not
    none_missed = missed_heights(df.assign(lidar=True), rows=(128,)).iloc[0]
    assert none_missed["objects"] == 0 and np.isnan(none_missed["median (px)"])


def _tiny_kitti(root, height=150, width=400):
    """One frame: a Car 20 px tall (counted: 25 px x 150/375 = 10) with 30 returns on a red patch, a Car 8 px tall
    (too small), a Cyclist and a DontCare; a grey image."""
    f, cx, cy = 300.0, width / 2, height / 2
    calib = Calibration(
        np.array([[f, 0, cx, 0], [0, f, cy, 0], [0, 0, 1, 0]]),
        np.eye(3),
        np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]], float),
    )
    car = Object3D("Car", 0.0, 0, 0.0, (0, 0, 0, 0), (1.5, 1.6, 4.0), (1.0, 1.5, 22.0), 0.0)
    uv = calib.rect_to_image(car.corners())
    bbox = (uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max())
    car = Object3D("Car", 0.0, 0, 0.0, bbox, car.dimensions, car.location, 0.0)
    small = Object3D("Car", 0.0, 0, 0.0, (300, 70, 316, 78), (1.5, 1.6, 4.0), (8.0, 1.5, 60.0), 0.0)
    cyclist = Object3D("Cyclist", 0.0, 0, 0.0, (40, 40, 70, 100), (1.7, 0.6, 1.8), (-6.0, 1.5, 10.0), 0.0)
    dontcare = Object3D("DontCare", -1.0, -1, -10.0, (350, 60, 380, 100), (-1.0,) * 3, (-1000.0,) * 3, -10.0)
    img = np.full((height, width, 3), 128, np.uint8)
    x0, y0, x1, y1 = (int(round(v)) for v in bbox)
    img[y0 : y1 + 1, x0 : x1 + 1] = (40, 40, 200)  # BGR: red
    rect = _to_rect(car, np.random.default_rng(2).uniform((-1.9, 0.2, -0.7), (1.9, 1.4, 0.7), (30, 3)))
    velo = np.stack([rect[:, 2], -rect[:, 0], -rect[:, 1], np.zeros(len(rect))], 1).astype(np.float32)
    for sub in ("image_2", "calib", "label_2", "velodyne"):
        (root / sub).mkdir(parents=True)
    cv2.imwrite(str(root / "image_2" / "000000.png"), img)
    calib.write(root / "calib" / "000000.txt")
    (root / "label_2" / "000000.txt").write_text("".join(o.to_line() + "\n" for o in (car, small, cyclist, dontcare)))
    velo.tofile(root / "velodyne" / "000000.bin")
    return bbox


def test_compute_counts_the_objects_the_ap_counts(tmp_path):
    bbox = _tiny_kitti(tmp_path / "training")
    df = compute(tmp_path, progress=False)
    assert list(df["condition"].cat.categories) == ["clear", "night", "rain_day", "rain_night", "glare"]
    assert len(df) == 5 and set(df["object"]) == {0} and set(df["class"]) == {"Car"}
    assert 10 <= bbox[3] - bbox[1] < 25
    row = df[df["condition"] == "clear"].iloc[0]
    assert row["returns"] == 30 and row["lidar"] and row["camera"] and row["bin"] == "15-30 m"
    assert row["distance"] == pytest.approx(np.hypot(1.0, 22.0))


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from ablate.data.generate import generate

    return generate(tmp_path_factory.mktemp("synth") / "set", 6, seed=5, progress=False)


def test_cli_on_generated_data_uses_its_masks(synth, tmp_path):
    main(["stats", "--root", str(synth), "--out", str(tmp_path / "out" / "synth")])
    text = (tmp_path / "out" / "synth.md").read_text()
    assert (tmp_path / "out" / "synth.png").stat().st_size > 0
    for heading in ("## Per condition", "## Per distance bin", "## Per class", "## Height of the objects the LiDAR"):
        assert heading in text
    rows = [
        line.split("|")[1].strip()
        for line in text.split("## Per distance bin")[0].splitlines()
        if line.startswith("| ")
    ][1:]
    assert rows == ["clear", "night", "rain_day", "rain_night", "glare", "all"]
    df = compute(synth, progress=False)
    assert df["frame"].nunique() <= 6 and len(df) % 5 == 0
    assert f"{len(df) // 5} objects" in text


def test_cli_on_real_kitti(kitti_root, tmp_path, capsys):
    main(["stats", "--root", str(kitti_root), "--out", str(tmp_path / "kitti"), "--frames", "4"])
    assert capsys.readouterr().out.split() == [str(tmp_path / "kitti.md"), str(tmp_path / "kitti.png")]
    text = (tmp_path / "kitti.md").read_text()
    # frames 000000-000003: a pedestrian 165 px tall and two cars (33 and 103 px); the 22 px car does not count
    assert "3 objects (2 Car, 1 Pedestrian)" in text
    clear = next(line for line in text.splitlines() if line.startswith("| clear "))
    assert [c.strip() for c in clear.split("|")[2:5]] == ["3", "100.0", "100.0"]  # objects, LiDAR hit, camera
    assert "--frames 4" in text


@pytest.mark.parametrize("where", ["missing", "road"])
def test_cli_names_a_root_it_cannot_use(where, kitti_root, tmp_path):
    root = tmp_path / "nowhere" if where == "missing" else kitti_root / "road"
    with pytest.raises(SystemExit) as err:
        main(["stats", "--root", str(root), "--out", str(tmp_path / "x")])
    message = str(err.value.code)
    assert message.startswith("error: ") and str(root) in message and "\n" not in message
    assert not (tmp_path / "x.md").exists()
