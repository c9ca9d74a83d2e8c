"""Fog metric (occflownet.eval.fog): known counts on hand-made grids, and an exact walk for 'crossed'."""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import FREE, GRID
from occflownet.eval.fog import FogMetric, crossed_voxels


def test_fog_counts_split_by_crossing():
    labels = np.full(GRID.shape, FREE, np.uint8)
    labels[10:20, 10:20, 2] = 11                     # 100 labelled voxels
    pred = np.full(GRID.shape, FREE, np.uint8)
    pred[10:20, 10:20, 2] = 11                       # all found ...
    pred[50:60, 50:60, 8:10] = 15                    # ... plus 200 fog voxels
    mask = np.zeros(GRID.shape, bool)
    mask[:100, :100] = True                          # everything above lies in the mask
    crossed = np.zeros(GRID.shape, bool)
    crossed[:40] = True                              # the labelled block is crossed, the fog block is not
    m = FogMetric()
    m.update(pred, labels, mask, crossed)
    out = m.compute()
    assert out["camera_mask"]["labelled"] == 100 and out["camera_mask"]["predicted"] == 300
    assert out["camera_mask"]["fog_factor"] == 3.0
    assert out["crossed"]["fog_factor"] == 1.0 and out["crossed"]["false_positive"] == 0
    assert out["never_crossed"]["labelled"] == 0 and out["never_crossed"]["false_positive"] == 200
    assert out["never_crossed"]["fog_factor"] is None
    assert abs(out["crossed_fraction"] - 40 / 100) < 1e-12
    assert abs(out["camera_mask"]["geometry_iou"] - 100 / 300) < 1e-12


def test_crossed_voxels_walk_from_origin_to_endpoint():
    # a ray along +x from the centre of voxel (100, 100, 2) for 2.0 m: voxels 100..105 (the end lies in 105)
    origin = np.array([[GRID.lower[0] + 100.5 * 0.4, GRID.lower[1] + 100.5 * 0.4, GRID.lower[2] + 2.5 * 0.4]])
    crossed = crossed_voxels(origin, np.array([[1.0, 0.0, 0.0]]), np.array([2.0]))
    assert crossed.sum() == 6 and crossed[100:106, 100, 2].all()
