"""Reporting (occflownet.eval.report): strict JSON and the per-class table."""
import json

import numpy as np
import pytest

from occflownet.occ3d import CLASS_NAMES
from occflownet.eval import OccupancyMetric, RayIoUMetric, dumps_json, format_table, to_json_ready

GT = np.array([4, 4, 4, 11, 11, 17, 17, 0], dtype=np.uint8).reshape(2, 2, 2)
PRED = np.array([4, 4, 11, 11, 17, 17, 4, 0], dtype=np.uint8).reshape(2, 2, 2)
MASK = np.array([1, 1, 1, 1, 0, 0, 0, 1], dtype=np.uint8).reshape(2, 2, 2)


def occupancy_result(mask=True):
    metric = OccupancyMetric()
    metric.update(PRED, GT, MASK if mask else None)
    return metric.compute()


def ray_result():
    metric = RayIoUMetric()
    metric.add_rays(np.array([4, 4, 17]), np.array([10.0, 11.5, 40.0]), np.array([4, 4, 4]),
                    np.array([10.2, 10.0, 12.0]))
    metric.samples, metric.rays_cast = 1, 5
    return metric.compute()


def test_to_json_ready_converts_numpy_and_non_finite():
    obj = {"a": np.float32(0.5), "b": float("nan"), "c": (np.int64(3), np.inf), 4: np.array([1.0, np.nan]),
           "d": np.bool_(True), "e": None, "f": "text"}
    assert to_json_ready(obj) == {"a": 0.5, "b": None, "c": [3, None], "4": [1.0, None], "d": True, "e": None,
                                  "f": "text"}


def test_dumps_json_is_strict_and_round_trips():
    result = {"occupancy": occupancy_result(), "rayiou": ray_result(), "checkpoint": "x.pt"}
    text = dumps_json(result)
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text)
    assert back["occupancy"]["camera_mask"]["iou_per_class"]["bus"] is None
    assert back["occupancy"]["camera_mask"]["miou"] == pytest.approx((2 / 3 + 0.5 + 1.0) / 3)
    assert back["rayiou"]["iou_per_class"]["car"] == pytest.approx([1 / 4, 2 / 3, 2 / 3])
    assert back["checkpoint"] == "x.pt"


def test_format_table_combined_and_from_json():
    result = {"occupancy": occupancy_result(), "rayiou": ray_result(), "checkpoint": "x.pt"}
    for res in (result, json.loads(dumps_json(result))):  # NaN or None both print as '-'
        table = format_table(res)
        lines = table.splitlines()
        header = lines[0].split()
        assert header == ["class", "IoU", "cam", "IoU", "all", "Ray@1m", "Ray@2m", "Ray@4m"]
        rows = {line[:24].strip(): line[24:].split() for line in lines[2:19]}
        assert list(rows) == [n + (" *" if n in ("bicycle", "bus", "car", "construction_vehicle", "motorcycle",
                                                   "pedestrian", "trailer", "truck") else "")
                              for n in CLASS_NAMES[:17]]
        assert rows["car *"] == ["66.67", "50.00", "25.00", "66.67", "66.67"]
        assert rows["bus *"] == ["-"] * 5
        assert rows["driveable_surface"] == ["50.00", "33.33", "-", "-", "-"]
        mean = next(line for line in lines if line.startswith("mean")).split()
        assert mean[1:] == ["72.22", "61.11", "25.00", "66.67", "66.67"]
        assert any(line.startswith("RayIoU: 52.78") for line in lines)
        assert any(line.startswith("Occ3D mIoU: 72.22 (camera mask)") for line in lines)


def test_format_table_single_results():
    table = format_table(occupancy_result(mask=False))
    assert "IoU cam" not in table and "IoU all" in table and "Ray@" not in table
    assert "Occ3D mIoU: 61.11 (all voxels)" in table
    table = format_table(ray_result())
    assert "Ray@1m" in table and "IoU all" not in table
    with pytest.raises(ValueError, match="no 'occ3d_miou' or 'rayiou'"):
        format_table({"something": 1})
