"""BEV flip augmentation of a training item (the official recipe's ``bda_aug_conf``: flip_dx_ratio = flip_dy_ratio =
0.5, no rotation or scaling): the ego frame is mirrored in x and/or y, and every geometric field of the item with it.

The images and intrinsics stay as they are; the mirror acts on the 3D side, as BEVDet's BEV data augmentation does
(its matrix multiplies the lifted frustum points): ``cam2ego`` becomes ``F · cam2ego`` (F = diag(sx, sy, 1, 1), a
reflection, so the mapped camera frame is left-handed, which the lifting and the LiDAR depth targets take as they
take any matrix), and so the network lifts each pixel to the mirrored place. The labels, rays and box moves are
mirrored to match. Needs a grid symmetric about x = 0 and y = 0 (Occ3D's: [-40, 40] m), so that voxel index i maps
to X - 1 - i.

Fields of an item (``occflownet.train.dataset``; all in the current ego frame) and what a flip does to them:
``cam2ego`` [6, 4, 4] → F·cam2ego; ``ray_origins``, ``ray_directions``, ``free_origins``, ``free_directions``
[R, 3] and ``depth_points`` [P, 3] → their x and/or y negated; ``occ_semantics``, ``occ_mask`` [X, Y, Z] and
``free_masks`` [T, X, Y, Z] → reversed along the flipped axes; ``flow`` (box moves: voxels int [M, 3], transforms
[K, 4, 4] ego → ego) → voxel indices mirrored, transforms F·T·F. Depths, labels and everything per ray or per
volume are unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from occflownet.occ3d import GRID, Grid

VECTOR_FIELDS = ("ray_origins", "ray_directions", "free_origins", "free_directions", "depth_points")
GRID_FIELDS = ("occ_semantics", "occ_mask")       # [X, Y, Z]
STACKED_GRID_FIELDS = ("free_masks",)             # [T, X, Y, Z]


@dataclass(frozen=True)
class BevFlip:
    """Mirror the ego frame's x axis (``x``) and/or y axis (``y``)."""

    x: bool = False
    y: bool = False

    @classmethod
    def draw(cls, rng: np.random.Generator, ratio: float = 0.5) -> "BevFlip":
        """Each axis flipped with probability ``ratio``, from ``rng`` (two draws, always, so later draws of the same
        generator do not depend on the outcome)."""
        u = rng.random(2)
        return cls(bool(u[0] < ratio), bool(u[1] < ratio))

    @property
    def signs(self) -> np.ndarray:
        """float32 [3]: (sx, sy, 1), -1 on a flipped axis."""
        return np.asarray([-1.0 if self.x else 1.0, -1.0 if self.y else 1.0, 1.0], np.float32)

    def apply(self, item: dict, grid: Grid = GRID) -> dict:
        """A copy of the training ``item`` (a dict of tensors, see the module docstring) with its geometry mirrored;
        the item itself when nothing is flipped."""
        if not (self.x or self.y):
            return item
        if not np.allclose(np.asarray(grid.lower[:2]), -np.asarray(grid.upper[:2])):
            raise ValueError(f"BEV flips need a grid symmetric about x = y = 0, got {grid.lower} .. {grid.upper}")
        signs = torch.from_numpy(self.signs)
        mirror = torch.diag(torch.cat([signs, torch.ones(1)]))                       # F = F⁻¹, [4, 4]
        out = dict(item)
        out["cam2ego"] = mirror @ item["cam2ego"]
        for key in VECTOR_FIELDS:
            if key in item:
                out[key] = item[key] * signs.to(item[key].dtype)
        axes = [a for a, flipped in ((0, self.x), (1, self.y)) if flipped]
        for key in GRID_FIELDS:
            if key in item:
                out[key] = torch.flip(item[key], axes)
        for key in STACKED_GRID_FIELDS:
            if key in item:
                out[key] = torch.flip(item[key], [a + 1 for a in axes])
        if "flow" in item:
            out["flow"] = self._flow(item["flow"], grid)
        return out

    def _flow(self, moves: dict, grid: Grid) -> dict:
        """Box moves (``occflownet.data.flow.flow_moves``' arrays) in the mirrored frame."""
        voxels = np.array(moves["voxels"], copy=True)
        for axis, flipped in ((0, self.x), (1, self.y)):
            if flipped:
                voxels[:, axis] = grid.shape[axis] - 1 - voxels[:, axis]
        mirror = np.diag(np.append(self.signs, 1.0)).astype(np.asarray(moves["transforms"]).dtype)
        return dict(moves, voxels=voxels, transforms=mirror @ np.asarray(moves["transforms"]) @ mirror)
