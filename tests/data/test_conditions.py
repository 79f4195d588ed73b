"""Complex-KITTI conditions and DGFN corruptions: deterministic per seed, and they change the input."""

import numpy as np
import pytest

from ablate.data.conditions import CONDITIONS, CORRUPTIONS, apply_condition, apply_corruption


@pytest.fixture
def image():
    rng = np.random.default_rng(0)
    grad = np.linspace(0.2, 0.9, 96, dtype=np.float32)
    return np.clip(grad[None, :, None] + rng.normal(0, 0.05, (48, 96, 3)), 0, 1).astype(np.float32)


@pytest.mark.parametrize("name", list(CONDITIONS))
def test_condition_deterministic_and_effective(image, name):
    a = apply_condition(name, image, np.random.default_rng(5))
    b = apply_condition(name, image, np.random.default_rng(5))
    c = apply_condition(name, image, np.random.default_rng(6))
    assert a.shape == image.shape and a.dtype == np.float32 and 0 <= a.min() and a.max() <= 1
    np.testing.assert_array_equal(a, b)
    if name == "clear":
        np.testing.assert_array_equal(a, image)
    else:
        assert np.abs(a - image).mean() > 0.02 and not np.array_equal(a, c)


def test_condition_direction(image):
    rng = lambda: np.random.default_rng(1)  # noqa: E731
    assert apply_condition("night", image, rng()).mean() < 0.6 * image.mean()
    assert apply_condition("glare", image, rng()).max() > 0.99
    assert apply_condition("glare", image, rng()).mean() > image.mean()
    assert (apply_condition("rain_day", image, rng()) < 0.15).all(-1).mean() > 0.03  # the dark wiper


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_corruptions(image, name):
    x = image.transpose(2, 0, 1)
    a = apply_corruption(name, x, np.random.default_rng(2), "rgb")
    np.testing.assert_array_equal(a, apply_corruption(name, x, np.random.default_rng(2), "rgb"))
    assert a.shape == x.shape and not np.array_equal(a, x)
    if name == "blank":
        assert not a.any()
    if name == "occlusion":
        assert (a == 0).all(0).sum() > 0.01 * x[0].size and (a[:, (a != 0).any(0)] == x[:, (a != 0).any(0)]).all()


def test_bad_names():
    with pytest.raises(KeyError, match="valid: clear, night"):
        apply_condition("fog", np.zeros((4, 4, 3), np.float32), np.random.default_rng(0))
    with pytest.raises(ValueError, match="camera only"):
        apply_corruption("noise", np.zeros((1, 4, 4), np.float32), np.random.default_rng(0), "dense_depth")
