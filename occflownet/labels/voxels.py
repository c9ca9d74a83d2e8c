"""From a keyframe's accumulated points to the three Occ3D arrays: semantics by majority vote, ``mask_lidar`` by
walking every beam, ``mask_camera`` by walking a ray from each camera to each observed voxel.

All arrays are [X, Y, Z] in the keyframe's ego frame (``LabelConfig.grid``, Occ3D's 200 × 200 × 16 by default). The
walks are ``occflownet.voxel_walk.walk_rays`` (exact; the numba engine when numba is installed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import FREE, Grid
from occflownet.labels.config import UNLABELLED
from occflownet.voxel_walk import walk_rays

MIN_CAMERA_DEPTH = 0.05  # m: a voxel centre must be this far in front of a camera to count as in its view


@dataclass(frozen=True)
class VoxelVote:
    """The majority vote. ``semantics`` uint8 [X, Y, Z]: the winning class of every voxel holding labelled points
    (at least ``min_points`` of them), FREE elsewhere; ``occupied`` bool: voxels holding at least ``min_points``
    points of any kind (labelled or not: what blocks a camera ray); ``unlabelled`` bool: occupied voxels whose
    points carry no class."""

    semantics: np.ndarray
    occupied: np.ndarray
    unlabelled: np.ndarray


def vote(points: np.ndarray, labels: np.ndarray, grid: Grid, min_points: int = 1) -> VoxelVote:
    """points float64 [M, 3] (ego frame), labels uint8 [M] (Occ3D class or UNLABELLED) → :class:`VoxelVote`.

    A voxel's class is the class most of its labelled points have; a tie goes to the lowest class index (Occ3D
    orders objects 0–10 before surfaces 11–16, so an object wins a tie against the ground under it)."""
    inside = grid.contains(points)
    ijk = grid.index_of(points[inside])
    flat = np.ravel_multi_index(ijk.T, grid.shape)
    lab = labels[inside].astype(np.int64)
    size = int(np.prod(grid.shape))
    count = np.bincount(flat, minlength=size)
    occupied = (count >= min_points).reshape(grid.shape)
    known = lab != UNLABELLED
    semantics = np.full(size, FREE, np.uint8)
    labelled_count = np.bincount(flat[known], minlength=size)
    if known.any():
        pairs, votes = np.unique(flat[known] * 256 + lab[known], return_counts=True)
        voxel, cls = pairs // 256, pairs % 256
        order = np.lexsort((cls, -votes, voxel))                # per voxel: most votes first, then lowest class
        first = np.ones(len(order), bool)
        first[1:] = voxel[order][1:] != voxel[order][:-1]
        win = order[first]
        enough = labelled_count[voxel[win]] >= min_points
        semantics[voxel[win][enough]] = cls[win][enough]
    semantics = semantics.reshape(grid.shape)
    return VoxelVote(semantics, occupied, occupied & (semantics == FREE))


def beam_free_space(origins: np.ndarray, ends: np.ndarray, grid: Grid) -> np.ndarray:
    """bool [X, Y, Z]: every voxel some beam passes through on its way from its origin to its end point (the end
    point's voxel included; origins, ends float64 [M, 3], ego frame)."""
    empty = np.zeros(grid.shape, np.uint8)
    if len(origins) == 0:
        return empty.astype(bool)
    return walk_rays(empty, origins, ends - origins, lower=grid.lower, voxel_size=grid.voxel_size,
                     t_end=np.ones(len(origins)), visited=True).visited


def lidar_mask(voted: VoxelVote, crossed: np.ndarray) -> np.ndarray:
    """``mask_lidar`` bool [X, Y, Z]: observed occupied (a labelled voxel of the vote) or observed free (crossed by
    a beam and holding no point). Occupied voxels without a class are unobserved."""
    return (voted.semantics != FREE) | (crossed & ~voted.occupied)


def camera_mask(observed: np.ndarray, occupied: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray,
                image_sizes: np.ndarray, grid: Grid) -> np.ndarray:
    """``mask_camera`` bool [X, Y, Z]: the voxels of ``observed`` (``mask_lidar``) that some camera sees.

    For every camera and every observed voxel whose centre projects into its image (at least MIN_CAMERA_DEPTH in
    front), a ray from the camera centre to the voxel centre is walked through ``occupied``; the voxels it visits,
    up to and including the first occupied one, are seen by that camera (Occ3D: "connect the voxel centre with the
    camera centre and cast a ray"). intrinsics [C, 3, 3] for images of image_sizes [C, 2] (width, height) pixels;
    cam2ego [C, 4, 4] into this ego frame (OpenCV camera axes)."""
    ijk = np.argwhere(observed)
    centers = np.asarray(grid.lower) + (ijk + 0.5) * grid.voxel_size
    origins, dirs = [], []
    for K, T, (w, h) in zip(intrinsics, cam2ego, image_sizes):
        pc = (centers - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / z + K[0, 1] * pc[:, 1] / z + K[0, 2]
            v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        ok = (z >= MIN_CAMERA_DEPTH) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        dirs.append(centers[ok] - T[:3, 3])
        origins.append(np.broadcast_to(T[:3, 3], dirs[-1].shape))
    o, d = np.concatenate(origins), np.concatenate(dirs)
    seen = walk_rays(occupied, o, d, lower=grid.lower, voxel_size=grid.voxel_size, t_end=np.ones(len(o)),
                     visited=True).visited
    return seen & observed
