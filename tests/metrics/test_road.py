"""RoadMaxF against hand-computed cases, a loop-based reference of the devkit's 256-threshold evaluation, a made-up
calibration projected by hand, and the real KITTI road frame um_000000 against a transliteration of the road
devkit's BEV lookup (BirdsEyeView.computeBEVLookUpTable / transformImage2BEV)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data import DataError
from ablate.data.kitti import Calibration, read_road_gt
from ablate.metrics import EVALUATORS
from ablate.metrics.road import RoadMaxF, bev_centres, bev_lookup, road_homography, road_scores

SMALL = {"res": 1.0, "x_range": (-2.0, 2.0), "z_range": (6.0, 10.0)}  # a 4 x 4 BEV grid


def reference(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[str, float]:
    """The devkit's evaluation written as loops: for each threshold k/255 count TP / FP / FN over all frames'
    valid cells (a cell is road when p >= k/255), then PRE, REC, F, MaxF and the 11-point AP."""
    curve = []
    for k in range(256):
        tp = fp = fn = 0
        for p, gt, valid in frames:
            for pv, gv, vv in zip(p.ravel(), gt.ravel(), valid.ravel()):
                if not vv:
                    continue
                hit = pv >= k / 255 if pv.dtype.kind == "f" else int(pv) >= k
                tp, fp, fn = tp + (hit and gv), fp + (hit and not gv), fn + (not hit and gv)
        pre = tp / (tp + fp + 1e-10)
        rec = tp / (tp + fn)
        curve.append((pre, rec, 2 * pre * rec / (pre + rec + 1e-10), k / 255))
    best = max(range(256), key=lambda k: (curve[k][2], -k))
    ap = 0.0
    for r in np.arange(0.0, 1.1, 0.1):
        ap += max(pre for pre, rec, _, _ in curve if rec >= r) / 11
    pre, rec, f, t = curve[best]
    return {"max_f": 100 * f, "ap": 100 * ap, "pre": 100 * pre, "rec": 100 * rec, "threshold": t}


def check(out: dict, expected: dict, abs_tol: float = 1e-4) -> None:
    for key, value in expected.items():
        assert out[key].item() == pytest.approx(value, abs=abs_tol), key


def test_perfect_prediction_scores_100():
    gt = torch.zeros(80, 40, dtype=torch.bool)
    gt[20:70, 10:25] = True
    metric = RoadMaxF(res=0.5, x_range=(-10, 10), z_range=(6, 46))
    metric.update(gt.float(), gt)
    check(metric.compute(), {"max_f": 100, "ap": 100, "pre": 100, "rec": 100, "threshold": 1 / 255})


def test_hand_counted_curve():
    # 8 road cells: 6 at p=0.9, 2 at 0.2; 8 other cells: 2 at 0.5, 6 at 0.1. Thresholds k/255:
    #   k <= 25: TP 8 FP 8 | 26..51: TP 8 FP 2 (P .8, R 1, F .8889) | 52..127: TP 6 FP 2 | 128..229: TP 6 FP 0
    #   (P 1, R .75, F .8571) | k >= 230: TP 0. MaxF at k = 26; AP = (8 levels r <= .7 at P 1 + 3 at P .8) / 11.
    gt = torch.tensor([[1, 1, 1, 1], [1, 1, 1, 1], [0, 0, 0, 0], [0, 0, 0, 0]])
    p = torch.tensor([[0.9, 0.9, 0.9, 0.9], [0.9, 0.9, 0.2, 0.2], [0.5, 0.5, 0.1, 0.1], [0.1, 0.1, 0.1, 0.1]])
    metric = RoadMaxF(**SMALL)
    metric.update(p, gt)
    check(
        metric.compute(),
        {"max_f": 100 * 1.6 / 1.8, "pre": 80, "rec": 100, "threshold": 26 / 255, "ap": 100 * (8 * 1.0 + 3 * 0.8) / 11},
    )
    assert metric.tp[[0, 26, 52, 128, 230]].tolist() == [8, 8, 6, 6, 0]
    assert metric.fp[[0, 26, 52, 128, 230]].tolist() == [8, 2, 2, 0, 0]
    assert metric.fn[[0, 26, 52, 128, 230]].tolist() == [0, 0, 2, 2, 8]


def test_scores_from_counts():
    tp, fp, fn = torch.zeros(256), torch.zeros(256), torch.zeros(256)
    tp[:], fp[:], fn[:] = 30, 70, 0  # threshold 0: everything is road
    tp[1:], fp[1:], fn[1:] = 20, 5, 10  # then P .8, R 2/3
    out = road_scores(tp, fp, fn)
    check(
        out,
        {
            "pre": 80,
            "rec": 100 * 2 / 3,
            "max_f": 100 * 2 * 0.8 * 2 / 3 / (0.8 + 2 / 3),
            "threshold": 1 / 255,
            "ap": 100 * (7 * 0.8 + 4 * 0.3) / 11,
        },
    )  # r <= .6 reach P .8; r >= .7 only threshold 0 (P .3)
    assert torch.isnan(road_scores(torch.zeros(256), torch.ones(256), torch.zeros(256))["max_f"])


def test_counts_are_summed_over_frames_not_averaged():
    # frame 1: 2 road cells found, 6 false alarms (F .4); frame 2: 8 road cells found exactly (F 1).
    # Summed at k >= 1: TP 10, FP 6, FN 0 -> F = 2 * .625 / 1.625 = 76.92 %, not the per-frame mean 70 %.
    gt1, gt2 = torch.zeros(4, 4), torch.zeros(4, 4)
    gt1[0, :2] = 1
    gt2[:2] = 1
    p1 = gt1.clone()
    p1.view(-1)[8:14] = 1
    assert (p1 * gt1).sum() == 2 and (p1 * (1 - gt1)).sum() == 6
    metric = RoadMaxF(**SMALL)
    metric.update(p1, gt1)
    metric.update(gt2.clone(), gt2)
    out = metric.compute()
    check(out, {"max_f": 100 * 2 * 0.625 / 1.625, "pre": 62.5, "rec": 100})
    assert out["max_f"].item() != pytest.approx(70.0, abs=1)
    batched = RoadMaxF(**SMALL)
    batched.update(torch.stack([p1, gt2])[:, None], torch.stack([gt1, gt2])[:, None])
    check(batched.compute(), {k: v.item() for k, v in out.items()})
    assert metric.tp.shape == metric.fp.shape == metric.fn.shape == (256,)  # no per-frame state


def test_dont_care_cells_are_excluded():
    gt = torch.zeros(4, 4, dtype=torch.bool)
    gt[:, :2] = True
    p = gt.float()
    p[0, 3], p[1, 0] = 1.0, 0.0  # one false alarm, one miss
    valid = torch.ones(4, 4, dtype=torch.bool)
    valid[0, 3] = valid[1, 0] = False
    masked = RoadMaxF(**SMALL)
    masked.update(p, gt, valid)
    check(masked.compute(), {"max_f": 100, "ap": 100})
    plain = RoadMaxF(**SMALL)
    plain.update(p, gt)
    check(plain.compute(), {"max_f": 100 * 7 / 8, "pre": 100 * 7 / 8, "rec": 100 * 7 / 8})


@pytest.mark.parametrize("quantised", [True, False])
def test_matches_loop_reference_on_random_frames(quantised):
    rng = np.random.default_rng(4)
    frames, metric = [], RoadMaxF(**SMALL)
    for _ in range(3):
        gt = rng.random((4, 4)) < 0.4
        noise = np.clip(gt * 0.35 + rng.random((4, 4)) * 0.65, 0, 1)
        p = np.round(noise * 255).astype(np.uint8) if quantised else noise
        valid = rng.random((4, 4)) > 0.15
        frames.append((p, gt, valid))
        metric.update(
            torch.from_numpy(p).float() / 255 if quantised else torch.from_numpy(p),
            torch.from_numpy(gt),
            torch.from_numpy(valid),
        )
    check(metric.compute(), reference(frames), abs_tol=1e-3)
    if quantised:  # uint8 levels k are read as k/255 exactly
        direct = RoadMaxF(**SMALL)
        for p, gt, valid in frames:
            direct.update(torch.from_numpy(p), torch.from_numpy(gt), torch.from_numpy(valid))
        assert torch.equal(direct.tp, metric.tp) and torch.equal(direct.fp, metric.fp)


def made_up_calib(road: bool = True) -> Calibration:
    """f = 100 px, principal point (50, 20); road frame: camera 1.5 m above the road, road origin 0.5 m to the
    camera's right and 0.25 m ahead of it (a road point (X, 0, Z) is the camera point (X - .5, 1.5, Z - .25))."""
    p2 = np.array([[100.0, 0, 50, 0], [0, 100, 20, 0], [0, 0, 1, 0]])
    cam_to_road = np.array([[1.0, 0, 0, 0.5], [0, 1, 0, -1.5], [0, 0, 1, 0.25]])
    return Calibration(
        P2=p2,
        R0_rect=np.eye(3),
        Tr_velo_to_cam=np.eye(3, 4),
        Tr_cam_to_road=cam_to_road if road else None,
        path="made_up.txt",
    )


GRID = {"res": 0.5, "x_range": (-2.0, 2.0), "z_range": (6.0, 10.0)}  # 8 x 8 cells


@pytest.mark.parametrize(
    "road, lookup, pixel",
    [
        (True, "devkit", (37, 52)),
        (False, "devkit", (37, 58)),
        (True, "nearest", (39, 53)),
        (False, "nearest", (38, 59)),
    ],
)
def test_warp_puts_a_ground_point_in_its_cell(road, lookup, pixel):
    # Grid res .5, x in [-2, 2], z in [6, 10]: cell (row 3, column 5) has centre x = .75, z = 8.25.
    # Road frame: u = 100 (.75 - .5) / (8.25 - .25) + 50 = 53.125, v = 100 * 1.5 / 8 + 20 = 38.75:
    #   devkit (1-based, truncated): (int(38.75) - 1, int(53.125) - 1) = (37, 52); nearest: (39, 53).
    # Level plane 1.5 m down: u = 100 * .75 / 8.25 + 50 = 59.09, v = 150 / 8.25 + 20 = 38.18:
    #   devkit (37, 58); nearest (38, 59).
    calib = made_up_calib(road)
    hom = road_homography(calib, None if road else 1.5)
    uvw = hom @ np.array([0.75, 8.25, 1.0])
    expected_uv = (53.125, 38.75) if road else (50 + 75 / 8.25, 20 + 150 / 8.25)
    assert uvw[:2] / uvw[2] == pytest.approx(expected_uv)
    image = torch.zeros(60, 100)
    image[pixel] = 1
    gt = torch.zeros(60, 100, dtype=torch.bool)
    metric = RoadMaxF(**GRID, camera_height=None if road else 1.5, lookup=lookup)
    metric.update(image, gt, calib=calib)
    assert metric.fp[1].item() == 1 and metric.tp[0].item() == 0  # one cell picked up the marked pixel
    idx, inside = bev_lookup(hom, (60, 100), **GRID, lookup=lookup)
    assert inside.all()
    hit = np.flatnonzero(image.numpy().ravel()[idx])
    assert hit.tolist() == [3 * 8 + 5]


@pytest.mark.parametrize(
    "cell, devkit, nearest",
    [
        # (row, column): centre (x, z) -> u = 100 (x - .5) / (z - .25) + 50, v = 150 / (z - .25) + 20
        ((3, 5), (37, 52), (39, 53)),  # (.75, 8.25): u = 53.125, v = 38.75
        ((0, 0), (34, 25), (36, 26)),  # (-1.75, 9.75): u = 50 - 225 / 9.5 = 26.316, v = 20 + 150 / 9.5 = 35.789
        ((7, 7), (44, 69), (45, 71)),  # (1.75, 6.25): u = 50 + 125 / 6 = 70.833, v = 45.0 exactly: devkit row 45 - 1
    ],
)
def test_lookup_pixels_by_hand(cell, devkit, nearest):
    hom = road_homography(made_up_calib())
    for lookup, (row, col) in (("devkit", devkit), ("nearest", nearest)):
        idx, inside = bev_lookup(hom, (60, 100), **GRID, lookup=lookup)
        k = cell[0] * 8 + cell[1]
        assert inside[k] and divmod(int(idx[k]), 100) == (row, col), lookup


@pytest.mark.parametrize("lookup, kept", [("devkit", 53), ("nearest", 52)])
def test_cells_outside_the_image_are_dont_care(lookup, kept):
    # Same grid and road frame, image 60 x 60: v = 150 / (z - .25) + 20 is in 35.8 .. 45 on every row, inside.
    # u = 100 (x - .5) / (z - .25) + 50: columns 0-5 (x - .5 <= .25) give u <= 50 + 25 / 6 = 54.2, inside on all 8
    # rows; column 7 (x - .5 = 1.25) gives u >= 50 + 125 / 9.5 = 63.2, outside on all. Column 6 (x - .5 = .75):
    # u = 57.9, 58.3, 58.8, 59.4 (z - .25 = 9.5, 9, 8.5, 8), then exactly 60.0 (z - .25 = 7.5), then 60.7, ...
    #   devkit: kept while u <= W = 60 (read 1-based): 5 rows, the fifth at pixel int(60.0) - 1 = 59; 48 + 5 = 53.
    #   nearest: kept while rint(u) < 60, i.e. u < 59.5: 4 rows; 48 + 4 = 52.
    metric = RoadMaxF(**GRID, lookup=lookup)
    metric.update(torch.ones(60, 60), torch.zeros(60, 60), calib=made_up_calib())
    assert metric.fp.tolist() == [kept] * 256 and metric.tp.sum() == metric.fn.sum() == 0
    idx, inside = bev_lookup(road_homography(made_up_calib()), (60, 60), **GRID, lookup=lookup)
    assert inside.reshape(8, 8)[:, 6].sum() == kept - 48
    if lookup == "devkit":
        assert divmod(int(idx[4 * 8 + 6]), 60) == (39, 59)  # (x, z) = (1.25, 7.75): u = 60.0, v = 40.0
    # Ground 9.75 m behind the camera projects into the image (v = 20 + 150 / -10 = 5) but is not seen.
    behind = RoadMaxF(res=1.0, x_range=(-1.0, 1.0), z_range=(-10.0, -9.0))
    behind.update(torch.ones(60, 100), torch.zeros(60, 100), calib=made_up_calib())
    assert behind.fp.sum() == 0


def test_missing_road_plane_is_a_loud_error():
    with pytest.raises(DataError, match="made_up.txt.*camera_height"):
        RoadMaxF().update(torch.zeros(60, 100), torch.zeros(60, 100), calib=made_up_calib(road=False))


@pytest.mark.parametrize(
    "preds, target, match",
    [
        (torch.full((4, 4), 2.0), torch.zeros(4, 4), "probabilities"),
        (torch.zeros(4, 4), torch.full((4, 4), 255), "0/1"),
        (torch.zeros(5, 4), torch.zeros(5, 4), r"must be \(4, 4\)"),
        (torch.zeros(4, 4), torch.zeros(3, 4, 4), "one shape"),
    ],
)
def test_bad_inputs_are_named(preds, target, match):
    with pytest.raises(ValueError, match=match):
        RoadMaxF(**SMALL).update(preds, target)


@pytest.fixture(scope="module")
def um_000000(kitti_root):
    root = kitti_root / "road" / "training"
    if not (root / "calib" / "um_000000.txt").is_file():
        pytest.skip(f"KITTI road frame um_000000 not found under {root}")
    road, valid = read_road_gt(root / "gt_image_2" / "um_road_000000.png")
    return Calibration.from_file(root / "calib" / "um_000000.txt"), road, valid


@pytest.mark.parametrize("lookup, offset", [("devkit", 1.5), ("nearest", 0.0)])
def test_real_calibration_round_trip(um_000000, lookup, offset):
    calib, road, valid = um_000000
    assert -calib.Tr_cam_to_road[1, 3] == pytest.approx(1.6, abs=0.1)  # the camera is ~1.6 m above the road
    hom = road_homography(calib)
    for x, z in ((0.0, 10.0), (-5.0, 30.0)):  # the fitted plane (pitched ~0.6 deg, origin 0.28 m ahead of the
        a, b = hom @ [x, z, 1], road_homography(calib, 1.6) @ [x, z, 1]  # camera) and a level one at 1.6 m:
        assert np.abs(a[:2] / a[2] - b[:2] / b[2]).max() < 15  # within ~10 px
    idx, inside = bev_lookup(hom, road.shape, lookup=lookup)
    inside = inside.reshape(800, 400)
    assert not inside[-1, 0] and not inside[-1, -1] and inside[:700, 200].all()  # a trapezoid
    bev = road.ravel()[idx].reshape(800, 400) & inside
    assert bev[700, 200] and 0.15 < bev[inside].mean() < 0.5  # the car stands on the road
    # back into the image: each road-plane pixel inside the grid reads the BEV cell it falls into, the pixel
    # (v, u) read from the image point (u, v) by the nearest pixel, from (u + 1.5, v + 1.5) by the devkit
    # (1-based, truncated: the projections in [u + 1, u + 2) take pixel u)
    v, u = np.nonzero(valid)
    xz = np.linalg.solve(hom, np.stack([u + offset, v + offset, np.ones_like(u)]).astype(float))
    x, z = xz[0] / xz[2], xz[1] / xz[2]
    row, col = np.floor((46 - z) / 0.05).astype(int), np.floor((x + 10) / 0.05).astype(int)
    ok = (xz[2] > 0) & (row >= 0) & (row < 800) & (col >= 0) & (col < 400)
    ok &= inside[row.clip(0, 799), col.clip(0, 399)]
    assert ok.sum() > 50_000
    assert (bev[row[ok], col[ok]] == road[v[ok], u[ok]]).mean() > 0.98
    metric = RoadMaxF(lookup=lookup)  # the ground truth as a prediction, warped with the calibration
    metric.update(torch.from_numpy(road).float(), torch.from_numpy(road), torch.from_numpy(valid), calib=calib)
    check(metric.compute(), {"max_f": 100, "ap": 100, "pre": 100, "rec": 100})
    assert metric.tp[0].item() == (bev & valid.ravel()[idx].reshape(800, 400)).sum()  # valid road cells


def devkit_bev(image: np.ndarray, calib: Calibration) -> np.ndarray:
    """The road devkit's transform2BEV of ``image`` (H, W) on its default grid, step by step as
    BirdsEyeView.computeBEVLookUpTable and transformImage2BEV take them: cell centres from np.arange, cast to
    float32, in column-major order; projected by columns (x, z, 1) of P2 . R0_rect . Tr_cam_to_road^-1; kept where
    1 <= u <= W and 1 <= v <= H; the cell (1-based z, x index) takes pixel (v - 1, u - 1), truncated. 0 elsewhere."""
    res, (x0, x1), (z0, z1) = 0.05, (-10.0, 10.0), (6.0, 46.0)
    xs, zs = np.meshgrid(np.arange(x0 + res / 2, x1, res), np.arange(z1 - res / 2, z0, -res))
    rows, cols = xs.shape
    x, z = xs.ravel(order="F").astype(np.float32), zs.ravel(order="F").astype(np.float32)
    rect, to_road = np.eye(4), np.eye(4)
    rect[:3, :3], to_road[:3] = calib.R0_rect, calib.Tr_cam_to_road
    tr33 = (calib.P2 @ rect @ np.linalg.inv(to_road))[:, [0, 2, 3]]
    uvw = tr33 @ np.vstack([x, z, np.ones_like(z)])
    u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
    h, w = image.shape
    keep = (v >= 1) & (u >= 1) & (v <= h) & (u <= w)
    z_ind, x_ind = np.mgrid[1 : rows + 1, 1 : cols + 1]
    z_ind, x_ind = z_ind.ravel(order="F")[keep], x_ind.ravel(order="F")[keep]
    out = np.zeros((rows, cols), image.dtype)
    out[z_ind - 1, x_ind - 1] = image[v[keep].astype(np.uint32) - 1, u[keep].astype(np.uint32) - 1]
    return out


def test_lookup_is_the_devkit_transform_on_a_real_frame(um_000000):
    calib, road, _ = um_000000
    pixel_ids = np.arange(1, road.size + 1).reshape(road.shape)  # each pixel its own value: which one a cell reads
    expected = devkit_bev(pixel_ids, calib)
    assert (expected > 0).sum() > 300_000
    for lookup, same in (("devkit", True), ("nearest", False)):
        idx, inside = bev_lookup(road_homography(calib), road.shape, lookup=lookup)
        got = np.where(inside, idx + 1, 0).reshape(800, 400)
        assert (got == expected).all() == same, lookup
    # the nearest pixel's centre is 1 to 2 px below and right of the devkit's, on every cell both keep
    near = np.where(inside, idx + 1, 0).reshape(800, 400)
    both = (near > 0) & (expected > 0)
    dv, du = np.divmod(near[both] - 1, road.shape[1]) - np.stack(np.divmod(expected[both] - 1, road.shape[1]))
    assert set(np.unique(dv)) <= {1, 2} and set(np.unique(du)) <= {1, 2}


def test_one_road_pixel_lands_in_the_devkit_cells(um_000000):
    calib, road, _ = um_000000
    pred = np.zeros(road.shape, np.float32)
    pred[250, 700] = 1.0  # road on one pixel, about 16 m ahead and 1.9 m to the right
    cells = np.flatnonzero(devkit_bev(pred, calib))
    assert len(cells) == 3  # the devkit's transform2BEV puts it in 3 cells
    metric = RoadMaxF()
    metric.update(torch.from_numpy(pred), torch.zeros(road.shape, dtype=torch.bool), calib=calib)
    assert metric.fp[1].item() == 3 and metric.fp[256 - 1].item() == 3
    for lookup in ("devkit", "nearest"):
        idx, inside = bev_lookup(road_homography(calib), road.shape, lookup=lookup)
        found = np.flatnonzero(inside & (idx == 250 * road.shape[1] + 700))
        assert (found.tolist() == cells.tolist()) == (lookup == "devkit"), lookup


def test_lookup_option_and_evaluator():
    assert RoadMaxF().evaluator == EVALUATORS["ablate.metrics.road"] == "kitti_road_devkit"
    assert RoadMaxF(lookup="nearest").evaluator == "kitti_road_nearest_pixel"
    with pytest.raises(ValueError, match=r"RoadMaxF: lookup must be one of \['devkit', 'nearest'\], got 'bilinear'"):
        RoadMaxF(lookup="bilinear")
    with pytest.raises(ValueError, match="lookup must be one of"):
        bev_lookup(np.eye(3), (10, 10), lookup="Devkit")


def test_bev_centres_orientation():
    x, z = bev_centres()
    assert x.shape == z.shape == (800, 400)
    assert (x[0, 0], z[0, 0]) == pytest.approx((-9.975, 45.975))  # far left at row 0, column 0
    assert (x[-1, -1], z[-1, -1]) == pytest.approx((9.975, 6.025))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_levels_are_the_threshold_search_at_every_threshold_and_its_neighbours(dtype):
    """:func:`levels` finds the count of thresholds k/255 a probability reaches without searching: at each
    threshold and the 64 floats on either side of it, 0, 1 and random values, placed at every offset of a long
    tensor (vectorised loops and their tails alike), it equals ``torch.bucketize(p, arange(256) / 255,
    right=True)``, what the counts were defined by."""
    from ablate.metrics.road import levels

    thresholds = torch.arange(256, dtype=dtype) / 255
    as_int = torch.int32 if dtype == torch.float32 else torch.int64
    steps = torch.arange(-64, 65, dtype=as_int)
    near = (thresholds.view(as_int)[:, None] + steps).view(dtype).flatten()  # below 0: negative floats, clamped
    edges = torch.cat([near.nan_to_num(0.0).clamp(0, 1), torch.tensor([0.0, 1.0], dtype=dtype)])
    gen = torch.Generator().manual_seed(0)
    for offset in range(17):  # each value at every position modulo the widest vector, and in a tail
        p = torch.cat(
            [torch.rand(offset, generator=gen, dtype=dtype), edges, torch.rand(1000, generator=gen, dtype=dtype)]
        )
        assert torch.equal(levels(p), torch.bucketize(p, thresholds, right=True)), offset
    assert levels(torch.tensor([0.0, 1.0], dtype=dtype)).tolist() == [1, 256]


def test_the_metric_counts_the_same_from_the_frames_histograms():
    """``update(histograms=...)`` (what the road task passes, keeping each test frame's histograms) counts exactly
    what ``update(preds, target, valid)`` counts for the same frames."""
    from ablate.metrics.road import frame_histograms

    gen = torch.Generator().manual_seed(2)
    shape = (3, 800, 400)
    target = torch.rand(shape, generator=gen) < 0.3
    preds = (0.3 * target + 0.7 * torch.rand(shape, generator=gen)).clamp(0, 1)
    valid = torch.rand(shape, generator=gen) < 0.9
    direct, counted = RoadMaxF(), RoadMaxF()
    direct.update(preds, target, valid)
    counted.update(histograms=frame_histograms(preds, target, valid))
    for name in ("tp", "fp", "fn"):
        assert torch.equal(getattr(direct, name), getattr(counted, name)), name
    with pytest.raises(ValueError, match="not both"):
        counted.update(preds, target, histograms=frame_histograms(preds, target, valid))
    # the metric's own per-frame histograms (what the task keeps) are those counts, its inputs checked as update's
    assert torch.equal(direct.histograms(preds, target, valid), frame_histograms(preds, target, valid))
    with pytest.raises(ValueError, match=r"BEV inputs must be \(800, 400\)"):
        direct.histograms(preds[:, :400], target[:, :400], valid[:, :400])
    with pytest.raises(ValueError, match="0/1 or bool"):
        direct.histograms(preds, target * 2.0, valid)
