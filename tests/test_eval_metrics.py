"""Occ3D mIoU (occflownet.eval.metrics) against hand-computed confusion matrices."""
import math
from pathlib import Path

import numpy as np
import pytest

from occflownet.occ3d import CLASS_NAMES, DYNAMIC_CLASSES, STATIC_CLASSES
from occflownet.eval import OccupancyMetric, confusion_matrix, iou_from_confusion, to_json_ready

SHARED = Path(__file__).resolve().parents[2] / "shared"
LABELS = SHARED / "data" / "occ3d-sample" / "labels.npz"

# Eight voxels, shape (2, 2, 2). Classes: 0 others, 4 car, 11 driveable_surface, 17 free.
GT = np.array([4, 4, 4, 11, 11, 17, 17, 0], dtype=np.uint8).reshape(2, 2, 2)
PRED = np.array([4, 4, 11, 11, 17, 17, 4, 0], dtype=np.uint8).reshape(2, 2, 2)
MASK = np.array([1, 1, 1, 1, 0, 0, 0, 1], dtype=np.uint8).reshape(2, 2, 2)  # hides voxels 4, 5, 6


def test_hand_made_confusion_and_ious():
    hist = confusion_matrix(PRED, GT)
    expected = np.zeros((18, 18), dtype=np.int64)
    for g, p in [(4, 4), (4, 4), (4, 11), (11, 11), (11, 17), (17, 17), (17, 4), (0, 0)]:
        expected[g, p] += 1
    assert np.array_equal(hist, expected)                         # counts (integers)

    metric = OccupancyMetric()
    metric.update(PRED, GT)
    res = metric.compute()["all_voxels"]
    iou = res["iou_per_class"]
    # car: TP 2 (voxels 0, 1), FP 1 (voxel 6, gt free), FN 1 (voxel 2, predicted road) → 2 / 4
    assert iou["car"] == pytest.approx(0.5)
    # driveable_surface: TP 1 (voxel 3), FP 1 (voxel 2), FN 1 (voxel 4, predicted free) → 1 / 3
    assert iou["driveable_surface"] == pytest.approx(1 / 3)
    assert iou["others"] == pytest.approx(1.0)
    # absent from both prediction and ground truth: NaN, skipped by the mean
    assert math.isnan(iou["bus"]) and math.isnan(iou["vegetation"])
    assert res["miou"] == pytest.approx((0.5 + 1 / 3 + 1.0) / 3)
    assert res["miou_static"] == pytest.approx((1.0 + 1 / 3) / 2)  # others, driveable_surface
    assert res["miou_dynamic"] == pytest.approx(0.5)  # car
    # occupied vs free: TP voxels 0, 1, 2, 3, 7; FP voxel 6; FN voxel 4 → 5 / 7
    assert res["geometry_iou"] == pytest.approx(5 / 7)
    assert res["voxels"] == 8
    assert len(iou) == 17 and "free" not in iou


def test_camera_mask_uint8_bool_and_0_255_agree():
    results = []
    for mask in (MASK, MASK.astype(bool), MASK * 255, MASK.astype(np.int64)):
        metric = OccupancyMetric()
        metric.update(PRED, GT, mask_camera=mask)
        results.append(metric.compute())
    cam = results[0]["camera_mask"]
    # car: TP 2, FP 0 (voxel 6 masked), FN 1 → 2/3; road: TP 1, FP 1, FN 0 (voxel 4 masked) → 1/2; others 1
    assert cam["iou_per_class"]["car"] == pytest.approx(2 / 3)
    assert cam["iou_per_class"]["driveable_surface"] == pytest.approx(0.5)
    assert cam["miou"] == pytest.approx((2 / 3 + 0.5 + 1.0) / 3)
    assert cam["voxels"] == 5
    for other in results[1:]:
        assert to_json_ready(other["camera_mask"]) == to_json_ready(cam)  # NaN → None: comparable
    # the unmasked accumulation is kept alongside
    assert results[0]["all_voxels"]["miou"] == pytest.approx((0.5 + 1 / 3 + 1.0) / 3)


def test_bad_masks_and_labels_raise():
    metric = OccupancyMetric()
    with pytest.raises(ValueError, match="mask_camera"):
        metric.update(PRED, GT, mask_camera=MASK * 2)  # values 0/2: neither 0/1 nor 0/255
    with pytest.raises(ValueError, match="mask_camera"):
        metric.update(PRED, GT, mask_camera=MASK[:1])
    with pytest.raises(ValueError, match="pred"):
        metric.update(PRED.astype(np.float32), GT)
    with pytest.raises(ValueError, match="pred"):
        metric.update(np.full_like(PRED, 18), GT)
    with pytest.raises(ValueError, match="gt"):
        metric.update(PRED, np.full_like(GT, 20))
    with pytest.raises(ValueError, match="shape"):
        metric.update(PRED, GT[:1])
    metric.update(PRED, GT, mask_camera=MASK)
    with pytest.raises(ValueError, match="for every sample"):
        metric.update(PRED, GT)  # mask given before, missing now
    with pytest.raises(ValueError, match="no samples"):
        OccupancyMetric().compute()


def test_gt_ignore_label_is_left_out_like_the_reference():
    gt = GT.copy()
    gt.flat[6] = 255  # the voxel that was a car false positive
    hist = confusion_matrix(PRED, gt)
    assert hist.sum() == 7
    assert iou_from_confusion(hist)[4] == pytest.approx(2 / 3)  # car: TP 2, FN 1, FP 0


def test_accumulation_equals_one_big_confusion():
    rng = np.random.default_rng(0)
    preds = [rng.integers(0, 18, size=(6, 5, 4), dtype=np.uint8) for _ in range(4)]
    gts = [rng.choice([0, 3, 4, 11, 17], size=(6, 5, 4)).astype(np.uint8) for _ in range(4)]
    masks = [rng.random((6, 5, 4)) < 0.6 for _ in range(4)]
    metric = OccupancyMetric()
    for p, g, m in zip(preds, gts, masks):
        metric.update(p, g, m)
    res = metric.compute()
    big_p, big_g, big_m = (np.concatenate(a, axis=0) for a in (preds, gts, masks))
    # the official accumulation, written out: bincount(18 * gt + pred) over masked voxels of the whole split
    hist = np.bincount(18 * big_g[big_m].astype(int) + big_p[big_m], minlength=324).reshape(18, 18)
    assert np.array_equal(np.array(res["camera_mask"]["confusion"]), hist)
    iou = np.diag(hist) / (hist.sum(0) + hist.sum(1) - np.diag(hist))
    assert res["camera_mask"]["miou"] == pytest.approx(np.nanmean(iou[:17]))
    assert res["camera_mask"]["miou_static"] == pytest.approx(np.nanmean(iou[list(STATIC_CLASSES)]))
    assert res["camera_mask"]["miou_dynamic"] == pytest.approx(np.nanmean(iou[list(DYNAMIC_CLASSES)]))
    # summing confusions is not averaging per-sample mIoUs
    per_sample = []
    for p, g, m in zip(preds, gts, masks):
        single = OccupancyMetric()
        single.update(p, g, m)
        per_sample.append(single.compute()["camera_mask"]["miou"])
    assert abs(np.mean(per_sample) - res["camera_mask"]["miou"]) > 1e-4
    # merging two halves equals one accumulator
    a, b = OccupancyMetric(), OccupancyMetric()
    for i, (p, g, m) in enumerate(zip(preds, gts, masks)):
        (a if i < 2 else b).update(p, g, m)
    a.merge(b)
    assert to_json_ready(a.compute()) == to_json_ready(res)


def test_all_classes_absent_give_nan_means():
    free = np.full((2, 2, 2), 17, dtype=np.uint8)
    metric = OccupancyMetric()
    metric.update(free, free)
    res = metric.compute()["all_voxels"]
    assert math.isnan(res["miou"]) and math.isnan(res["miou_static"]) and math.isnan(res["geometry_iou"])
    assert all(math.isnan(v) for v in res["iou_per_class"].values())


@pytest.mark.skipif(not LABELS.exists(), reason=f"shared Occ3D sample not found at {LABELS}")
def test_real_sample_perfect_and_shifted_prediction():
    data = np.load(LABELS)
    gt, mask = data["semantics"], data["mask_camera"]
    metric = OccupancyMetric()
    metric.update(gt, gt, mask)
    res = metric.compute()
    present = {CLASS_NAMES[c] for c in np.unique(gt) if c < 17}
    for section in ("camera_mask", "all_voxels"):
        ious = res[section]["iou_per_class"]
        assert all(ious[n] == 1.0 for n in present)
        assert all(math.isnan(ious[n]) for n in ious if n not in present)
        assert res[section]["miou"] == 1.0
    assert res["camera_mask"]["voxels"] == int(mask.sum())
    assert res["all_voxels"]["voxels"] == gt.size
    shifted = OccupancyMetric()
    shifted.update(np.roll(gt, 2, axis=0), gt, mask)
    assert 0.2 < shifted.compute()["camera_mask"]["miou"] < 0.95
