"""KittiAP against hand-computed cases and a loop-by-loop transliteration of the KITTI object devkit's
evaluate_object.cpp (2017; its ``cleanData`` with the older 2D devkit's height rule as the ``2d_2012`` option)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ablate.data.dataset import CLASSES
from ablate.data.kitti import Object3D
from ablate.metrics import EVALUATORS
from ablate.metrics.kitti import LABEL_NAMES, KittiAP, thresholds


def image(gts=(), dets=()) -> tuple[dict, dict]:
    """gts: (type, xyxy, occluded, truncated); dets: (type, xyxy, score) -> (pred, target) of KittiAP.update."""
    target = {
        "boxes": torch.tensor([g[1] for g in gts], dtype=torch.float64).reshape(-1, 4),
        "labels": torch.tensor([LABEL_NAMES.index(g[0]) for g in gts], dtype=torch.long),
        "occluded": torch.tensor([g[2] for g in gts], dtype=torch.long),
        "truncated": torch.tensor([g[3] for g in gts], dtype=torch.float64),
    }
    pred = {
        "boxes": torch.tensor([d[1] for d in dets], dtype=torch.float64).reshape(-1, 4),
        "labels": torch.tensor([LABEL_NAMES.index(d[0]) for d in dets], dtype=torch.long),
        "scores": torch.tensor([d[2] for d in dets], dtype=torch.float64),
    }
    return pred, target


CAR = (100.0, 100.0, 150.0, 150.0)  # 50 px tall: easy


def found_cars(n: int) -> list[tuple[dict, dict]]:
    """n images, each one easy Car found exactly, scores 0.01 .. n/100 (all below 0.99)."""
    return [image([("Car", CAR, 0, 0.0)], [("Car", CAR, (i + 1) / 100)]) for i in range(n)]


def evaluate(images, **kwargs) -> dict[str, float]:
    """KittiAP over ``images`` (pairs of ``image``), one update per image; values as floats."""
    metric = KittiAP(**kwargs)
    for p, t in images:
        metric.update([p], [t])
    return {k: v.item() for k, v in metric.compute().items()}


# ---- the reference: eval.cpp (cleanData, computeStatistics, getThresholds, eval_class), one loop per loop ----
MIN_H, MAX_OCC, MAX_TRUNC = (40, 25, 25), (0, 1, 2), (0.15, 0.3, 0.5)
OVERLAP = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}


def ref_boxoverlap(a, b, criterion=-1):
    w, h = min(a[2], b[2]) - max(a[0], b[0]), min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter, a_area, b_area = w * h, (a[2] - a[0]) * (a[3] - a[1]), (b[2] - b[0]) * (b[3] - b[1])
    return inter / (a_area + b_area - inter) if criterion == -1 else inter / a_area


def ref_clean(cls, gts, dets, diff, scale, devkit="2017"):
    ignored_gt, ignored_det, n_gt = [], [], 0
    for typ, box, occ, trunc in gts:
        if typ == cls:
            valid = 1
        elif (cls, typ) in (("Pedestrian", "Person_sitting"), ("Car", "Van")):
            valid = 0
        else:
            valid = -1
        height = box[3] - box[1]  # double in evaluate_object.cpp
        too_short = height <= MIN_H[diff] * scale if devkit == "2017" else height < MIN_H[diff] * scale
        ignore = occ > MAX_OCC[diff] or trunc > MAX_TRUNC[diff] or too_short
        if valid == 1 and not ignore:
            ignored_gt.append(0)
            n_gt += 1
        elif valid == 0 or (ignore and valid == 1):
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
    dc = [g for g in gts if g[0] == "DontCare"]
    for typ, box, _ in dets:
        height = abs(box[1] - box[3])
        height = int(height) if scale == 1 else height  # int32_t in eval.cpp
        ignored_det.append(1 if height < MIN_H[diff] * scale else 0 if typ == cls else -1)
    return ignored_gt, dc, ignored_det, n_gt


def ref_statistics(cls, gts, dets, dc, ignored_gt, ignored_det, compute_fp, thresh=0.0):
    no_detection, tp, fp, fn, v = -10000000.0, 0, 0, 0, []
    assigned = [False] * len(dets)
    ignored_threshold = [compute_fp and d[2] < thresh for d in dets]
    for i, g in enumerate(gts):
        if ignored_gt[i] == -1:
            continue
        det_idx, valid_detection, max_iou, assigned_ignored_det = -1, no_detection, 0.0, False
        for j, d in enumerate(dets):
            if ignored_det[j] == -1 or assigned[j] or ignored_threshold[j]:
                continue
            overlap = ref_boxoverlap(d[1], g[1])
            if not compute_fp and overlap > OVERLAP[cls] and d[2] > valid_detection:
                det_idx, valid_detection = j, d[2]
            elif (
                compute_fp
                and overlap > OVERLAP[cls]
                and (overlap > max_iou or assigned_ignored_det)
                and ignored_det[j] == 0
            ):
                max_iou, det_idx, valid_detection, assigned_ignored_det = overlap, j, 1, False
            elif compute_fp and overlap > OVERLAP[cls] and valid_detection == no_detection and ignored_det[j] == 1:
                det_idx, valid_detection, assigned_ignored_det = j, 1, True
        if valid_detection == no_detection and ignored_gt[i] == 0:
            fn += 1
        elif valid_detection != no_detection and (ignored_gt[i] == 1 or ignored_det[det_idx] == 1):
            assigned[det_idx] = True
        elif valid_detection != no_detection:
            tp += 1
            v.append(dets[det_idx][2])
            assigned[det_idx] = True
    if compute_fp:
        for i in range(len(dets)):
            if not (assigned[i] or ignored_det[i] == -1 or ignored_det[i] == 1 or ignored_threshold[i]):
                fp += 1
        nstuff = 0
        for c in dc:
            for j, d in enumerate(dets):
                if assigned[j] or ignored_det[j] in (-1, 1) or ignored_threshold[j]:
                    continue
                if ref_boxoverlap(d[1], c[1], 0) > OVERLAP[cls]:
                    assigned[j] = True
                    nstuff += 1
        fp -= nstuff
    return tp, fp, fn, v


def ref_thresholds(v, n_groundtruth, n_sample_pts=41):
    v, t, current_recall = sorted(v, reverse=True), [], 0.0
    for i in range(len(v)):
        l_recall = (i + 1) / n_groundtruth
        r_recall = (i + 2) / n_groundtruth if i < len(v) - 1 else l_recall
        if (r_recall - current_recall) < (current_recall - l_recall) and i < len(v) - 1:
            continue
        t.append(v[i])
        current_recall += 1.0 / (n_sample_pts - 1.0)
    return t


def ref_eval_class(cls, frames, diff, scale=1.0, devkit="2017"):
    """(ap11, ap40); frames: list of (gts, dets) in the tuple forms of ``image``. -1 with no counted GT."""
    n_gt, v, cleaned = 0, [], []
    for gts, dets in frames:
        ig_gt, dc, ig_det, n = ref_clean(cls, gts, dets, diff, scale, devkit)
        n_gt += n
        cleaned.append((gts, dets, dc, ig_gt, ig_det))
        v += ref_statistics(cls, gts, dets, dc, ig_gt, ig_det, False)[3]
    if n_gt == 0:
        return -1.0, -1.0  # the metric's reading; the devkit prints 0
    thresholds = ref_thresholds(v, n_gt)
    pr = [[0, 0, 0] for _ in thresholds]
    for gts, dets, dc, ig_gt, ig_det in cleaned:
        for t, thresh in enumerate(thresholds):
            tp, fp, fn, _ = ref_statistics(cls, gts, dets, dc, ig_gt, ig_det, True, thresh)
            pr[t] = [pr[t][0] + tp, pr[t][1] + fp, pr[t][2] + fn]
    precision = [0.0] * 41
    for i, (tp, fp, _) in enumerate(pr):
        precision[i] = tp / (tp + fp) if tp + fp else 0.0
    for i in range(len(thresholds)):
        precision[i] = max(precision[i:])
    return sum(precision[0:41:4]) / 11 * 100, sum(precision[1:]) / 40 * 100


def random_frames(seed: int, n_images: int = 60, on_thresholds: float = 0.0) -> list[tuple[list, list]]:
    """KITTI-like frames: every type, occlusion 0-3, truncation 0-0.6, heights around the thresholds, objects in
    overlapping clusters, 1-3 jittered detections of most objects (some with another label), random false
    positives, some inside DontCare boxes, scores with ties. ``on_thresholds``: the share of objects put on a
    whole-pixel row with a height of exactly 25 or 40 px or 0.01 px off, with a detection of the same box."""
    rng = np.random.default_rng(seed)
    types = ["Car", "Pedestrian", "Cyclist", "Van", "Person_sitting", "DontCare"]
    frames = []
    for _ in range(n_images):
        gts, dets, x, y = [], [], rng.uniform(0, 1000), rng.uniform(100, 250)
        for _ in range(rng.integers(0, 7)):
            typ = types[rng.choice(6, p=[0.4, 0.2, 0.1, 0.1, 0.05, 0.15])]
            if rng.random() < 0.5:  # a new cluster, else next to the previous object
                x, y = rng.uniform(0, 1000), rng.uniform(100, 250)
            x, y = x + rng.normal(0, 15), y + rng.normal(0, 5)
            w, h = rng.uniform(10, 150), rng.uniform(10, 110) if rng.random() < 0.5 else rng.uniform(15, 45)
            exact = rng.random() < on_thresholds
            if exact:
                y, h = float(round(y)), float(rng.choice([24.99, 25.0, 25.01, 39.99, 40.0, 40.01]))
            box = tuple(np.round([x, y, x + w, y + h], 2).tolist())
            gts.append((typ, box, int(rng.integers(0, 4)), float(np.round(rng.uniform(0, 0.6), 2))))
            if exact and typ != "DontCare":
                dets.append(
                    (
                        {"Van": "Car", "Person_sitting": "Pedestrian"}.get(typ, typ),
                        box,
                        float(np.round(rng.random(), 2)),
                    )
                )
            for _ in range(rng.integers(1, 4) if rng.random() < 0.8 else 0):
                label = {"Van": "Car", "Person_sitting": "Pedestrian", "DontCare": "Car"}.get(typ, typ)
                label = label if rng.random() < 0.85 else types[rng.integers(0, 3)]
                j = rng.normal(0, 0.08 * min(w, h), 4) if typ != "DontCare" else [w / 4, h / 4, -w / 4, -h / 4]
                dets.append((label, tuple(np.round(np.add(box, j), 2).tolist()), float(np.round(rng.random(), 2))))
        for _ in range(rng.integers(0, 4)):
            x, y, w, h = rng.uniform(0, 1000), rng.uniform(100, 250), rng.uniform(10, 150), rng.uniform(10, 110)
            dets.append((types[rng.integers(0, 3)], (x, y, x + w, y + h), float(np.round(rng.random(), 2))))
        frames.append((gts, dets))
    return frames


# ---- hand-made cases ----
def test_perfect_detector_scores_100_with_enough_ground_truths():
    ped = (300.0, 100.0, 320.0, 160.0)
    frames = [
        image(
            [("Car", CAR, 0, 0.0), ("Pedestrian", ped, 0, 0.0)],
            [("Car", CAR, (i + 1) / 100), ("Pedestrian", ped, (i + 1) / 100)],
        )
        for i in range(50)
    ]
    out = evaluate(frames)
    for cls in ("Car", "Pedestrian"):
        for level in ("easy", "moderate", "hard"):
            assert out[f"{cls}/{level}/ap11"] == pytest.approx(100.0)
            assert out[f"{cls}/{level}/ap40"] == pytest.approx(100.0)
    assert out["Cyclist/moderate/ap40"] == -1.0  # no Cyclist GT: undefined, left out of the mean
    assert out["ap11"] == out["ap40"] == out["hard/ap40"] == pytest.approx(100.0)


def test_single_ground_truth_fills_only_the_first_point():
    """getThresholds puts the one TP score at recall point 0: precision curve [p, 0, ..., 0]."""
    assert evaluate(found_cars(1))["Car/easy/ap11"] == pytest.approx(100 / 11)
    assert evaluate(found_cars(1))["Car/easy/ap40"] == 0.0
    tp_and_fp = [image([("Car", CAR, 0, 0.0)], [("Car", CAR, 0.5), ("Car", (300, 100, 350, 150), 0.9)])]
    out = evaluate(tp_and_fp)  # at the TP's score, the higher FP is counted too: precision 1/2
    assert out["Car/easy/ap11"] == pytest.approx(50 / 11)
    assert out["Car/easy/ap40"] == 0.0


def test_eleven_and_forty_point_ap_by_hand():
    # 40 GTs all found: 40 thresholds fill points 0..39 with precision 1, point 40 stays 0.
    out = evaluate(found_cars(40))
    assert out["Car/easy/ap40"] == pytest.approx(100 * 39 / 40)
    assert out["Car/easy/ap11"] == pytest.approx(100 * 10 / 11)
    # plus one FP above every TP: precision (k+1)/(k+2) at threshold k, interpolated to 40/41 at points 0..39
    out = evaluate(found_cars(40) + [image([], [("Car", CAR, 0.99)])])
    assert out["Car/easy/ap40"] == pytest.approx(100 * 39 / 41)
    assert out["Car/easy/ap11"] == pytest.approx(100 * 400 / 451)


def test_detection_on_dontcare_is_not_a_false_positive():
    region = (400.0, 100.0, 500.0, 200.0)
    inside = image([("DontCare", region, -1, -1.0)], [("Car", (420.0, 120.0, 470.0, 170.0), 0.99)])
    assert evaluate(found_cars(41) + [inside])["Car/easy/ap40"] == pytest.approx(100.0)
    # the same detection without the region, or with only 60 % of it inside (Car needs > 70 %): an FP on top
    alone = image([], [("Car", (420.0, 120.0, 470.0, 170.0), 0.99)])
    partly = image([("DontCare", region, -1, -1.0)], [("Car", (380.0, 120.0, 430.0, 170.0), 0.99)])
    for case in (alone, partly):
        out = evaluate(found_cars(41) + [case])
        assert out["Car/easy/ap40"] == pytest.approx(100 * 41 / 42)
        assert out["Car/easy/ap11"] == pytest.approx(100 * 41 / 42)


def test_car_detection_on_a_van_is_not_a_false_positive():
    van = image([("Van", (400.0, 100.0, 460.0, 160.0), 0, 0.0)], [("Car", (400.0, 100.0, 460.0, 160.0), 0.99)])
    assert evaluate(found_cars(41) + [van])["Car/moderate/ap40"] == pytest.approx(100.0)
    cyclist = image([("Cyclist", (400.0, 100.0, 460.0, 160.0), 0, 0.0)], [("Car", (400.0, 100.0, 460.0, 160.0), 0.99)])
    assert evaluate(found_cars(41) + [cyclist])["Car/moderate/ap40"] == pytest.approx(100 * 41 / 42)


def test_short_ground_truth_ignored_in_easy_counts_in_moderate():
    missed = image([("Car", (400.0, 100.0, 450.0, 130.0), 0, 0.0)])  # 30 px: below easy's 40, above 25
    out = evaluate(found_cars(41) + [missed])
    assert out["Car/easy/ap40"] == pytest.approx(100.0)
    # moderate: 41 of 42 found, 40 thresholds, precision 1 at points 0..39
    assert out["Car/moderate/ap40"] == out["Car/hard/ap40"] == pytest.approx(100 * 39 / 40)
    assert out["Car/moderate/ap11"] == pytest.approx(100 * 10 / 11)


def test_short_detection_is_ignored_only_where_it_is_below_the_minimum_height():
    short_fp = image([], [("Car", (400.0, 100.0, 450.0, 130.0), 0.99)])
    out = evaluate(found_cars(41) + [short_fp])
    assert out["Car/easy/ap40"] == pytest.approx(100.0)
    assert out["Car/moderate/ap40"] == pytest.approx(100 * 41 / 42)


GT41, SHORT, FULL = (400.0, 100.0, 450.0, 141.0), (400.0, 101.5, 450.0, 141.0), (405.0, 100.0, 455.0, 141.0)
# a 41 px Car; a 39.5 px detection on it (IoU 0.96, too short for easy) and a 41 px one shifted 5 px (IoU 0.82)


def test_precision_pass_prefers_a_detection_that_is_not_too_short():
    # the full-height detection scores higher: the TP of both passes; the short one is ignored, not a FP
    out = evaluate(found_cars(41) + [image([("Car", GT41, 0, 0.0)], [("Car", SHORT, 0.995), ("Car", FULL, 0.999)])])
    assert out["Car/easy/ap40"] == pytest.approx(100.0)
    # the short one scores higher: the threshold pass takes it (no TP score: 41 of 42, so 40 thresholds), while
    # the precision pass still finds the full-height TP: precision 1 at points 0..39
    out = evaluate(found_cars(41) + [image([("Car", GT41, 0, 0.0)], [("Car", SHORT, 0.999), ("Car", FULL, 0.995)])])
    assert out["Car/easy/ap40"] == pytest.approx(100 * 39 / 40)
    assert out["Car/easy/ap11"] == pytest.approx(100 * 10 / 11)


def test_short_detection_of_another_class_absorbs_a_ground_truth_as_in_the_devkit():
    """cleanData marks a too-short detection ignored (1) whatever its class: in easy the short Pedestrian
    detection, scoring higher, takes the Car in the threshold pass as the short Car did above; in moderate it is
    tall enough, so only a Pedestrian, and the Car detection is the TP of both passes."""
    case = image([("Car", GT41, 0, 0.0)], [("Pedestrian", SHORT, 0.999), ("Car", FULL, 0.995)])
    out = evaluate(found_cars(41) + [case])
    assert out["Car/easy/ap40"] == pytest.approx(100 * 39 / 40)
    assert out["Car/moderate/ap40"] == pytest.approx(100.0)


def test_ties_go_to_the_first_detection_in_input_order():
    # a Van between two Car detections of equal IoU (0.82); the precision pass gives it the first, d0, leaving d1
    # for the Car (IoU 0.89; d0 has only 0.59 with it): no FN, no FP. Taking the last would cost a FN and a FP.
    van, car = (100.0, 100.0, 150.0, 150.0), (108.0, 100.0, 158.0, 150.0)
    d0, d1 = (95.0, 100.0, 145.0, 150.0), (105.0, 100.0, 155.0, 150.0)
    case = image([("Van", van, 0, 0.0), ("Car", car, 0, 0.0)], [("Car", d0, 0.9), ("Car", d1, 0.5)])
    assert evaluate(found_cars(41) + [case])["Car/easy/ap40"] == pytest.approx(100.0)


def test_thresholds_follow_get_thresholds_including_float_ties():
    """Every count of TPs m <= n GTs up to 100 (ties such as 45 GTs, 14 TPs included)."""
    for n in range(1, 101):
        for m in range(1, n + 1):
            v = np.arange(m, dtype=float) / 1000
            assert thresholds(v, n).tolist() == ref_thresholds(v.tolist(), n), (n, m)


def test_overlap_threshold_is_per_class():
    # shifted 10 px: IoU 40/60 = 0.67, a match for a Pedestrian (> 0.5), not for a Car (> 0.7)
    gt, det = (100.0, 100.0, 150.0, 200.0), (110.0, 100.0, 160.0, 200.0)
    frames = [
        image(
            [("Car", gt, 0, 0.0), ("Pedestrian", gt, 0, 0.0)],
            [("Car", det, (i + 1) / 100), ("Pedestrian", det, (i + 1) / 100)],
        )
        for i in range(41)
    ]
    out = evaluate(frames)
    assert out["Car/easy/ap40"] == 0.0
    assert out["Pedestrian/easy/ap40"] == pytest.approx(100.0)
    assert out["easy/ap40"] == pytest.approx(50.0)
    # IoU exactly 0.5 is not a Pedestrian match (eval.cpp: overlap > MIN_OVERLAP)
    ped, half = (100.0, 100.0, 130.0, 160.0), (110.0, 100.0, 140.0, 160.0)
    frames = [image([("Pedestrian", ped, 0, 0.0)], [("Pedestrian", half, (i + 1) / 100)]) for i in range(41)]
    assert evaluate(frames)["Pedestrian/easy/ap40"] == 0.0


def test_height_thresholds_scale_with_image_height():
    missed = image([("Car", (400.0, 100.0, 450.0, 121.0), 0, 0.0)])  # 21 px: easy only at >= 20 (half size)
    frames = found_cars(41) + [missed]
    assert evaluate(frames)["Car/easy/ap40"] == pytest.approx(100.0)
    assert evaluate(frames, image_height=187.5)["Car/easy/ap40"] == pytest.approx(100 * 39 / 40)


# ---- boxes on the height thresholds: cleanData ignores a GT not taller than the minimum (2017), shorter (2d_2012) ----
def test_height_rule_of_each_devkit():
    heights = np.array([24.99, 25.0, 25.01, 39.99, 40.0, 40.01])
    assert KittiAP().gt_tall_enough(heights, 1).tolist() == [False, False, True, True, True, True]  # > 25
    assert KittiAP().gt_tall_enough(heights, 0).tolist() == [False, False, False, False, False, True]  # > 40
    old = KittiAP(devkit="2d_2012")
    assert old.gt_tall_enough(heights, 1).tolist() == [False, True, True, True, True, True]  # >= 25
    assert old.gt_tall_enough(heights, 0).tolist() == [False, False, False, False, True, True]  # >= 40
    assert KittiAP(image_height=750.0).gt_tall_enough(np.array([50.0, 50.01]), 1).tolist() == [False, True]


def missed_car(height: float, difficulty: int | None = None) -> tuple[dict, dict]:
    """An image with one undetected Car GT ``height`` px tall (occluded 0, truncated 0; y from 100.0, so 25.0 and
    40.0 are exact and 24.99 / 25.01 come out 0.01 px off); ``difficulty``: given as that input instead."""
    pred, target = image([("Car", (400.0, 100.0, 450.0, 100.0 + height), 0, 0.0)])
    if difficulty is not None:
        target = {"boxes": target["boxes"], "labels": target["labels"], "difficulty": torch.tensor([difficulty])}
    return pred, target


# With found_cars(41) (41 easy Cars, each found) and one missed Car:
#   missed GT counted: 42 GTs, 41 TPs -> getThresholds gives 40 thresholds, precision 1 at points 0..39, 0 at 40:
#                      ap40 = 39/40 = 97.5, ap11 = 10/11 = 90.91 (points 0, 4, ..., 36; point 40 is 0)
#   missed GT ignored: 41 GTs, 41 TPs -> 41 thresholds, precision 1 at every point: ap40 = ap11 = 100
COUNTED, IGNORED = (100 * 39 / 40, 100 * 10 / 11), (100.0, 100.0)


@pytest.mark.parametrize(
    "devkit, height, moderate",
    [
        ("2017", 24.99, IGNORED),
        ("2017", 25.0, IGNORED),
        ("2017", 25.01, COUNTED),
        ("2d_2012", 24.99, IGNORED),
        ("2d_2012", 25.0, COUNTED),
        ("2d_2012", 25.01, COUNTED),
    ],
)
def test_ground_truth_on_the_moderate_and_hard_minimum(devkit, height, moderate):
    # counted GTs at moderate and hard: 41 + (1 if moderate is COUNTED else 0); at easy (> 40 or >= 40) always 41
    for difficulty in (None, 1 if height >= 25 else -1):  # by occlusion / truncation, or as boxes2d gives it
        out = evaluate(found_cars(41) + [missed_car(height, difficulty)], devkit=devkit)
        for level in ("moderate", "hard"):
            assert (out[f"Car/{level}/ap40"], out[f"Car/{level}/ap11"]) == pytest.approx(moderate), (level, difficulty)
        assert (out["Car/easy/ap40"], out["Car/easy/ap11"]) == pytest.approx(IGNORED)


@pytest.mark.parametrize(
    "devkit, height, easy",
    [
        ("2017", 39.99, IGNORED),
        ("2017", 40.0, IGNORED),
        ("2017", 40.01, COUNTED),
        ("2d_2012", 39.99, IGNORED),
        ("2d_2012", 40.0, COUNTED),
        ("2d_2012", 40.01, COUNTED),
    ],
)
def test_ground_truth_on_the_easy_minimum(devkit, height, easy):
    # counted GTs at easy: 41 + (1 if easy is COUNTED else 0); at moderate and hard (> 25) always 42
    for difficulty in (None, 0 if height >= 40 else 1):
        out = evaluate(found_cars(41) + [missed_car(height, difficulty)], devkit=devkit)
        assert (out["Car/easy/ap40"], out["Car/easy/ap11"]) == pytest.approx(easy), difficulty
        assert (out["Car/moderate/ap40"], out["Car/moderate/ap11"]) == pytest.approx(COUNTED), difficulty


def test_default_ignores_a_25_px_ground_truth_at_moderate_and_hard_without_dropping_it():
    exact = (400.0, 100.0, 450.0, 125.0)
    out = evaluate(found_cars(41) + [image([("Car", exact, 0, 0.0)])])
    assert out["Car/moderate/ap40"] == out["Car/hard/ap40"] == pytest.approx(100.0)  # 41 counted GTs, all found
    # still a GT: a detection of it (25 px, tall enough at moderate) is absorbed, neither TP nor FP
    out = evaluate(found_cars(41) + [image([("Car", exact, 0, 0.0)], [("Car", exact, 0.99)])])
    assert out["Car/moderate/ap40"] == out["Car/hard/ap40"] == pytest.approx(100.0)


# A lone Car detection (no GT) scoring 0.99, above the 41 found Cars (0.01 .. 0.41):
#   a FP (int(height) >= minimum): at threshold k, k + 1 TPs and 1 FP -> precision (k + 1) / (k + 2), interpolated
#       to its maximum 41/42 at every point: ap40 = ap11 = 100 * 41/42 = 97.62
#   ignored (int(height) < minimum, e.g. int(24.99) = 24): precision 1 at every point: 100
FP = (100 * 41 / 42, 100 * 41 / 42)


@pytest.mark.parametrize("devkit", ["2017", "2d_2012"])  # the detection rule is the same in both
@pytest.mark.parametrize(
    "height, moderate, easy",
    [
        (24.99, IGNORED, IGNORED),
        (25.0, FP, IGNORED),
        (25.01, FP, IGNORED),
        (39.99, FP, IGNORED),
        (40.0, FP, FP),
        (40.01, FP, FP),
    ],
)
def test_detection_on_the_minimum_heights(devkit, height, moderate, easy):
    lone = image([], [("Car", (400.0, 100.0, 450.0, 100.0 + height), 0.99)])
    out = evaluate(found_cars(41) + [lone], devkit=devkit)
    assert (out["Car/moderate/ap40"], out["Car/moderate/ap11"]) == pytest.approx(moderate)
    assert (out["Car/hard/ap40"], out["Car/hard/ap11"]) == pytest.approx(moderate)
    assert (out["Car/easy/ap40"], out["Car/easy/ap11"]) == pytest.approx(easy)


# ---- the reference on random cases ----
@pytest.mark.parametrize(
    "seed,image_height,on_thresholds,devkit",
    [
        (0, 375.0, 0.0, "2017"),
        (1, 375.0, 0.0, "2017"),
        (2, 250.0, 0.0, "2017"),
        (5, 375.0, 0.4, "2017"),
        (6, 375.0, 0.4, "2d_2012"),
        (7, 375.0, 0.0, "2d_2012"),
    ],
)
def test_matches_devkit_transliteration_on_random_frames(seed, image_height, on_thresholds, devkit):
    frames = random_frames(seed, on_thresholds=on_thresholds)
    out = evaluate([image(g, d) for g, d in frames], image_height=image_height, devkit=devkit)
    inner = 0
    for cls in CLASSES:
        for k, level in enumerate(("easy", "moderate", "hard")):
            ap11, ap40 = ref_eval_class(cls, frames, k, image_height / 375, devkit)
            assert out[f"{cls}/{level}/ap11"] == pytest.approx(ap11, abs=1e-4), (cls, level)
            assert out[f"{cls}/{level}/ap40"] == pytest.approx(ap40, abs=1e-4), (cls, level)
            inner += 0 < ap40 < 100 and ap11 != ap40
    assert inner >= 5  # the cases are not degenerate


def test_difficulty_input_equals_occlusion_and_truncation():
    frames = random_frames(3)
    scale = 250.0 / 375
    by_level = []
    for gts, dets in frames:
        p, t = image(gts, dets)
        objs = [Object3D(g[0], g[3], g[2], 0.0, g[1], (1.0, 1.0, 1.0), (0.0, 0.0, 10.0), 0.0) for g in gts]
        t = {
            "boxes": t["boxes"],
            "labels": t["labels"],
            "difficulty": torch.tensor([o.difficulty_at(scale) for o in objs], dtype=torch.long),
        }
        by_level.append((p, t))
    assert evaluate(by_level, image_height=250.0) == evaluate([image(g, d) for g, d in frames], image_height=250.0)


# ---- accumulation, sync, edge cases ----
def test_evaluator_names_the_devkit():
    assert KittiAP().evaluator == EVALUATORS["ablate.metrics.kitti"] == "kitti_object_devkit_2017"
    assert KittiAP(devkit="2d_2012").evaluator == "kitti_object_devkit_2d_2012"


def test_two_updates_equal_one_update_and_gathered_states_equal_all_ranks():
    frames = [image(g, d) for g, d in random_frames(4, n_images=20)]
    one, two = KittiAP(), KittiAP()
    one.update([p for p, _ in frames], [t for _, t in frames])
    for p, t in frames:
        two.update([p], [t])
    assert {k: v.item() for k, v in one.compute().items()} == {k: v.item() for k, v in two.compute().items()}
    synced, local = KittiAP(), KittiAP()
    synced.update([p for p, _ in frames], [t for _, t in frames])
    synced._sync_dist(lambda t, group=None: [t, t])  # what Metric.sync runs under DDP, two ranks
    assert isinstance(synced.pred_boxes, torch.Tensor)
    local.update([p for p, _ in frames] * 2, [t for _, t in frames] * 2)
    out_s, out_l = synced.compute(), local.compute()
    for key in out_l:
        assert out_s[key].item() == pytest.approx(out_l[key].item()), key


def test_empty_cases():
    with pytest.warns(UserWarning, match="before the ``update``"):
        assert all(v.item() == -1.0 for v in KittiAP().compute().values())
    no_dets = evaluate([image([("Car", CAR, 0, 0.0)])])
    assert no_dets["Car/easy/ap40"] == 0.0 and no_dets["Pedestrian/easy/ap40"] == -1.0
    assert no_dets["easy/ap40"] == 0.0


def test_bad_options_and_inputs_are_named():
    with pytest.raises(ValueError, match="Truck"):
        KittiAP(classes=("Car", "Truck"))
    with pytest.raises(ValueError, match="image_height"):
        KittiAP(image_height=0)
    with pytest.raises(ValueError, match=r"devkit must be one of \['2017', '2d_2012'\], got '2012'"):
        KittiAP(devkit="2012")
    p, t = image([("Car", CAR, 0, 0.0)])
    with pytest.raises(KeyError, match="difficulty"):
        KittiAP().update([p], [{"boxes": t["boxes"], "labels": t["labels"]}])
    with pytest.raises(KeyError, match="scores"):
        KittiAP().update([{"boxes": p["boxes"], "labels": p["labels"]}], [t])
    with pytest.raises(ValueError, match="label 9"):
        KittiAP().update([p], [dict(t, labels=torch.tensor([9]))])
