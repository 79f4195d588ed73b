"""The generated LiDAR's detection model (received power, threshold, mixed pixels, materials) and LiDAR weather."""

import numpy as np
import pytest

from ablate.data import lidar_physics as physics
from ablate.data.generate import calibration, scan
from ablate.data.lidar_weather import apply_lidar_weather
from ablate.data.raycast import CAMERA_HEIGHT
from ablate.data.synth import PAINTS, _Boxes, _car


def test_threshold_matches_the_datasheet_ranges():
    assert physics.max_range(0.10) == pytest.approx(50.0, abs=0.1)  # pavement-like, 10 %
    assert physics.max_range(0.80) == pytest.approx(120.0, abs=0.1)  # cars and foliage, 80 %
    assert physics.max_range(0.03) < 30.0  # dark paint
    # Lambert halves the power at 60 deg; glossy paint keeps cos^8 of it; glass (rho 0) returns nothing.
    p0 = physics.received_power(0.5, 1.0, 20.0)
    assert physics.received_power(0.5, 0.5, 20.0) == pytest.approx(0.5 * p0)
    assert physics.received_power(0.5, 0.5, 20.0, gloss=physics.GLOSS_EXPONENT) == pytest.approx(0.5**8 * p0)
    assert physics.received_power(0.0, 1.0, 5.0) == 0 and physics.received_power(0.5, 1.0, np.inf) == 0


def test_mixed_pixel_is_the_power_weighted_range():
    t = physics.THRESHOLD
    power = np.array([[4 * t, 0.1 * t], [4 * t, 0.1 * t]])
    dist = np.array([[10.0, 10.0], [30.0, np.inf]])
    ok, rng, refl = physics.combine(power, dist, np.array([[0.2, 0.2], [0.6, 0.0]]))
    assert ok.tolist() == [True, False]
    assert rng[0] == pytest.approx(20.0) and refl[0] == pytest.approx(0.4)


def _scene_with_car(z: float, paint: int, yaw: float = -np.pi / 2) -> dict:
    boxes = _Boxes()
    _car(boxes, 0, np.random.default_rng(0), 0.0, CAMERA_HEIGHT, z, (4.2, 1.5, 1.8), yaw, None, paint=paint)
    s = {
        "offset": 0.0,
        "curvature": 0.0,
        "road_half_width": 5.0,
        "sidewalk": 2.0,
        "curb": 0.0,
        "road_refl": 0.25,
        "border_refl": 0.25,
    }
    boxes.into(s)
    return s


def _points_on_car(scene: dict, z: float) -> np.ndarray:
    pts = scan(scene, np.random.default_rng(1), 128, 416)
    rect = calibration(128, 416).velo_to_rect(pts[:, :3])
    on = (np.abs(rect[:, 0]) < 1.2) & (np.abs(rect[:, 2] - z) < 2.4) & (rect[:, 1] < CAMERA_HEIGHT - 0.1)
    return rect[on]


def test_dark_paint_vanishes_with_range_and_white_does_not():
    black = [k for k, p in enumerate(PAINTS) if p[2][1] <= 0.06][0]
    white = 0
    assert len(_points_on_car(_scene_with_car(8.0, black), 8.0)) >= 10
    assert len(_points_on_car(_scene_with_car(45.0, black), 45.0)) == 0
    assert len(_points_on_car(_scene_with_car(45.0, white), 45.0)) >= 10


def test_glass_cabin_returns_nothing_but_the_roof():
    scene = _scene_with_car(10.0, 0, yaw=0.0)  # side-on: the cabin's side windows face the sensor
    pts = _points_on_car(scene, 10.0)
    body_top = CAMERA_HEIGHT - 0.2 - 0.75
    body = (pts[:, 1] > body_top + 0.05).sum()
    cabin_side = ((pts[:, 1] < body_top - 0.1) & (pts[:, 1] > body_top - 0.45)).sum()
    assert body > 30 and cabin_side < 0.1 * body


def test_lidar_weather():
    rng = np.random.default_rng(0)
    n = 5000
    d = rng.uniform(2, 80, n)
    az = rng.uniform(-0.7, 0.7, n)
    pts = np.stack([d * np.cos(az), d * np.sin(az), rng.uniform(-1.5, 1, n), rng.uniform(0.2, 0.6, n)], 1)
    same = apply_lidar_weather("fog", pts, np.random.default_rng(3), severity=0.0)
    assert np.array_equal(same, pts.astype(np.float32))
    fog = apply_lidar_weather("fog", pts, np.random.default_rng(3))
    again = apply_lidar_weather("fog", pts, np.random.default_rng(3))
    assert np.array_equal(fog, again)
    r = np.linalg.norm(fog[:, :3], axis=1)
    assert (r > 50).sum() < 0.05 * (d > 50).sum()  # fog (150 m visibility) ends far returns
    assert (r < 8).sum() >= 800  # near-range clutter
    rain = apply_lidar_weather("rain", pts, np.random.default_rng(3))
    assert len(fog) < len(pts) and (np.linalg.norm(rain[:, :3], axis=1) > 50).sum() > (r > 50).sum()
    with pytest.raises(KeyError, match="unknown LiDAR weather 'snow'"):
        apply_lidar_weather("snow", pts, rng)
