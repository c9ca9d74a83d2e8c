"""occflownet.labels.stats on hand-made grids whose figures are counted by hand."""
import math

import numpy as np
import pytest

from occflownet.labels.stats import label_stats, mean_stats, truth_agreement

# Occ3D class ids (occflownet.occ3d): 4 car, 10 truck, 11 driveable surface, 14 terrain, 15 manmade, 16 vegetation,
# 17 free; the ground classes are 11 (driveable surface), 12 (other flat), 13 (sidewalk) and 14 (terrain).
CAR, TRUCK, DRIVEABLE, TERRAIN, MANMADE, VEGETATION, FREE = 4, 10, 11, 14, 15, 16, 17
SHAPE = (4, 3, 2)                                    # 24 voxels, 12 columns, 2 layers


def _grid(cells: dict, fill: int = 0) -> np.ndarray:
    grid = np.full(SHAPE, fill, np.uint8)
    for ijk, value in cells.items():
        grid[ijk] = value
    return grid


# six occupied voxels: ground in columns (0, 0) and (2, 1), a car voxel in mask_camera, three others outside it
SEMANTICS = _grid({(0, 0, 0): DRIVEABLE, (1, 0, 1): CAR, (2, 1, 0): TERRAIN, (3, 2, 1): MANMADE, (3, 2, 0): CAR,
                   (2, 2, 1): VEGETATION}, fill=FREE)
# five voxels in mask_camera: two occupied ((0,0,0), (1,0,1)), three free ((0,1,0), (1,1,0) in layer 0, (0,1,1))
MASK_CAMERA = _grid({(0, 0, 0): 1, (1, 0, 1): 1, (0, 1, 0): 1, (0, 1, 1): 1, (1, 1, 0): 1})
# mask_lidar: mask_camera less (0, 1, 1), plus (2, 1, 0)
MASK_LIDAR = _grid({(0, 0, 0): 1, (1, 0, 1): 1, (0, 1, 0): 1, (1, 1, 0): 1, (2, 1, 0): 1})


def test_label_stats_by_hand():
    stats = label_stats(SEMANTICS, MASK_LIDAR, MASK_CAMERA)
    assert stats == {"mask_camera": 5, "mask_camera_share": pytest.approx(5 / 24), "mask_camera_outside_lidar": 1,
                     "occupied_in_camera": 2, "free_in_camera": 3, "occupied": 6,
                     "occupied_share_in_camera": pytest.approx(2 / 6), "ground_columns": 2, "columns": 12,
                     "free_in_camera_by_layer": [2, 1]}


def test_label_stats_counts_every_ground_class_and_nothing_else():
    """A column is a ground column when any of its voxels is driveable surface, other flat, sidewalk or terrain."""
    for cls, ground in ((10, False), (11, True), (12, True), (13, True), (14, True), (15, False), (FREE, False)):
        semantics = _grid({(1, 1, 1): cls}, fill=FREE)
        assert label_stats(semantics, MASK_LIDAR, MASK_CAMERA)["ground_columns"] == int(ground), cls


def test_label_stats_of_an_empty_grid():
    empty = np.zeros(SHAPE, np.uint8)
    stats = label_stats(np.full(SHAPE, FREE, np.uint8), empty, empty)
    assert stats["occupied"] == 0 and stats["occupied_share_in_camera"] == 0.0 and stats["mask_camera"] == 0
    assert stats["free_in_camera_by_layer"] == [0, 0] and stats["ground_columns"] == 0


def test_truth_agreement_by_hand():
    """Inside mask_camera the labels have (0,0,0) driveable and (1,0,1) car occupied; the truth has (0,0,0)
    driveable, (1,0,1) truck and (0,1,0) vegetation, and (3,2,1) outside the mask (not counted): both occupied at
    two voxels (precision 2/2), the same class at one of them (1/2), two of the truth's three found (2/3)."""
    truth = _grid({(0, 0, 0): DRIVEABLE, (1, 0, 1): TRUCK, (0, 1, 0): VEGETATION, (3, 2, 1): MANMADE}, fill=FREE)
    agreement = truth_agreement(SEMANTICS, MASK_CAMERA, truth)
    assert agreement == {"occupied": 2, "true_positive": 2, "precision": 1.0, "class_agreement": 0.5,
                         "recall": pytest.approx(2 / 3)}


def test_truth_agreement_without_overlap():
    truth = _grid({(0, 1, 0): VEGETATION}, fill=FREE)               # occupied where the labels are free
    agreement = truth_agreement(SEMANTICS, MASK_CAMERA, truth)
    assert agreement["true_positive"] == 0 and agreement["precision"] == 0.0 and agreement["recall"] == 0.0
    assert math.isnan(agreement["class_agreement"])
    none = truth_agreement(np.full(SHAPE, FREE, np.uint8), MASK_CAMERA, truth)
    assert none["occupied"] == 0 and none["precision"] == 0.0           # nothing occupied: 0, not a division by 0


def test_mean_stats_averages_numbers_and_lists_per_entry():
    rows = [{"mask_camera": 4, "free_in_camera_by_layer": [1, 2], "precision": 0.5},
            {"mask_camera": 6, "free_in_camera_by_layer": [3, 6], "precision": 1.0}]
    assert mean_stats(rows) == {"mask_camera": 5.0, "free_in_camera_by_layer": [2.0, 4.0], "precision": 0.75}
    two = [label_stats(SEMANTICS, MASK_LIDAR, MASK_CAMERA), label_stats(SEMANTICS, MASK_CAMERA, MASK_CAMERA)]
    mean = mean_stats(two)
    assert mean["mask_camera_outside_lidar"] == 0.5 and mean["free_in_camera_by_layer"] == [2.0, 1.0]
