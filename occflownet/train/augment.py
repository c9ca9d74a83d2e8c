"""Augmentations of a training item, each drawn per item from the item's generator and applied to its fields:

- :class:`BevFlip`, the official recipe's ``bda_aug_conf`` (flip_dx_ratio = flip_dy_ratio = 0.5, no rotation or
  scaling): the ego frame is mirrored in x and/or y, and every geometric field of the item with it;
- :class:`BevRotation` (beyond the paper): the ego frame turned about z by a multiple of 90°, the same way (with the
  flips, any of the eight symmetries of the square grid; both move voxels onto voxels, so nothing is resampled);
- :class:`ImageAug`, the official recipe's image augmentation (``data_config``: resize jitter, horizontal crop
  position, horizontal flip, rotation, drawn per camera): each image is warped by an affine map of its pixel
  coordinates and its intrinsics follow, so the scene's geometry is unchanged;
- :class:`Photometric` (beyond the paper): each image's brightness, contrast and saturation jittered, drawn per
  camera, its geometry untouched.

BEV flip. The images and intrinsics stay as they are; the mirror acts on the 3D side, as BEVDet's BEV data
augmentation does (its matrix multiplies the lifted frustum points): ``cam2ego`` becomes ``F · cam2ego`` (F = diag(sx,
sy, 1, 1), a reflection, so the mapped camera frame is left-handed, which the lifting and the LiDAR depth targets take
as they take any matrix), and so the network lifts each pixel to the mirrored place. The labels, rays and box moves
are mirrored to match. Needs a grid symmetric about x = 0 and y = 0 (Occ3D's: [-40, 40] m), so that voxel index i
maps to X - 1 - i.

Fields of an item (``occflownet.train.dataset``; all in the current ego frame) and what a flip does to them:
``cam2ego`` [6, 4, 4] → F·cam2ego; ``ray_origins``, ``ray_directions``, ``free_origins``, ``free_directions``
[R, 3] and ``depth_points`` [P, 3] → their x and/or y negated; ``occ_semantics``, ``occ_mask`` [X, Y, Z] and
``free_masks`` [T, X, Y, Z] → reversed along the flipped axes; ``flow`` (box moves: voxels int [M, 3], transforms
[K, 4, 4] ego → ego) → voxel indices mirrored, transforms F·T·F. Depths, labels and everything per ray or per
volume are unchanged.

Image augmentation. Pixel coordinates follow the OpenCV convention of the contract (integer coordinates are pixel
centres). Camera v's map A_v (3 × 3, last row 0 0 1) takes a pixel of the stored image to its place in the
augmented one; the augmented image at q is the stored image at A_v⁻¹ q (bilinear, black outside the stored image,
the same size as it), and its intrinsics are A_v · K_v, so a camera-frame point still lands on the pixel that shows
it, at the same z-depth (the lifting inverts any 3 × 3 intrinsics; the LiDAR depth targets project with the
network's feature intrinsics, derived from these). Only ``images`` [6, H, W, 3] and ``intrinsics`` [6, 3, 3] change.
A_v = R · F · S, drawn per camera as BEVDet's ``sample_augmentation`` draws per camera:
S scales by s about the bottom centre of the image (the official keeps the bottom rows of the resized image) and
shifts it sideways by up to the width it gained or lost (the official's random crop position); F mirrors it
horizontally with probability 0.5; R rotates it about the image centre by an angle in [-5.4°, 5.4°].
s ∈ [1 - 0.06 / 0.88, 1 + 0.11 / 0.88]: the official jitter (-0.06, 0.11) added to its base resize 1408 / 1600 =
0.88, taken relative to that base.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from occflownet.occ3d import GRID, Grid

VECTOR_FIELDS = ("ray_origins", "ray_directions", "free_origins", "free_directions", "depth_points")
GRID_FIELDS = ("occ_semantics", "occ_mask")       # [X, Y, Z]
STACKED_GRID_FIELDS = ("free_masks",)             # [T, X, Y, Z]

SCALE_RANGE = (1.0 - 0.06 / 0.88, 1.0 + 0.11 / 0.88)  # official resize jitter (-0.06, 0.11) over its base 0.88
ROTATION_DEG = 5.4                                  # official rot (-5.4, 5.4)
IMAGE_FLIP_RATIO = 0.5                              # official flip: True (np.random.choice([0, 1]))
# Photometric jitter, each part applied with probability PHOTOMETRIC_RATIO: the ranges of mmdet's
# PhotoMetricDistortion defaults (BEVFormer's multi-view pipeline), without its hue jitter and channel swap.
BRIGHTNESS_DELTA = 32.0                             # added to every channel, in [-32, 32] (uint8 levels)
CONTRAST_RANGE = (0.5, 1.5)                         # every channel multiplied by a factor in this range
SATURATION_RANGE = (0.5, 1.5)                       # a colour's distance from its grey × a factor in it
PHOTOMETRIC_RATIO = 0.5
GREY_WEIGHTS = (0.299, 0.587, 0.114)                # ITU-R BT.601 luma of RGB


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
        return apply_xy_map(item, np.diag(self.signs[:2]).astype(np.int64), grid)


@dataclass(frozen=True)
class BevRotation:
    """Turn the ego frame about its z axis by ``quarter_turns`` × 90° (counter-clockwise seen from above: the point
    (x, y) moves to (-y, x) for one turn), every geometric field of the item with it, as :class:`BevFlip` mirrors
    them. A quarter turn maps the grid's voxels onto voxels (a square grid centred on the ego), so labels and box
    moves are moved exactly, with no resampling."""

    quarter_turns: int = 0

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "BevRotation":
        """0, 1, 2 or 3 quarter turns, uniform, from one draw of ``rng``."""
        return cls(int(rng.integers(4)))

    @property
    def matrix(self) -> np.ndarray:
        """int64 [2, 2]: the map of (x, y)."""
        c, s = ((1, 0), (0, 1), (-1, 0), (0, -1))[self.quarter_turns % 4]
        return np.array([[c, -s], [s, c]], np.int64)

    def apply(self, item: dict, grid: Grid = GRID) -> dict:
        """A copy of the training ``item`` with its geometry turned; the item itself for no turn."""
        return apply_xy_map(item, self.matrix, grid)


def apply_xy_map(item: dict, matrix: np.ndarray, grid: Grid = GRID) -> dict:
    """A copy of the training ``item`` in the ego frame whose (x, y) are ``matrix`` int [2, 2] (a signed permutation:
    a flip, a quarter turn or both) times the old ones, z unchanged; the item itself for the identity. The frame's
    map T = [[matrix, 0], [0, 1]] (4 × 4) acts as the module docstring says for a flip: ``cam2ego`` → T·cam2ego, the
    vectors → T·v, the grids [X, Y, Z] (and [T, X, Y, Z]) moved voxel by voxel, box moves' voxels moved and their
    transforms T·M·T⁻¹. Needs a grid symmetric about x = 0 and y = 0, and square when x and y swap."""
    matrix = np.asarray(matrix, np.int64)
    if np.array_equal(matrix, np.eye(2, dtype=np.int64)):
        return item
    if not np.allclose(np.asarray(grid.lower[:2]), -np.asarray(grid.upper[:2])) or \
            (matrix[0, 0] == 0 and grid.shape[0] != grid.shape[1]):
        raise ValueError(f"BEV flips and turns need a grid symmetric about x = y = 0 (and square for a turn), got "
                         f"{grid.lower} .. {grid.upper}")
    t = np.eye(4)
    t[:2, :2] = matrix
    out = dict(item)
    out["cam2ego"] = torch.from_numpy(t).to(item["cam2ego"].dtype) @ item["cam2ego"]
    linear = torch.from_numpy(t[:3, :3].T)
    for key in VECTOR_FIELDS:
        if key in item:
            out[key] = item[key] @ linear.to(item[key].dtype)
    source_i, source_j = _source_voxels(matrix, grid.shape[:2])
    for key in GRID_FIELDS:
        if key in item:
            out[key] = item[key][source_i, source_j]
    for key in STACKED_GRID_FIELDS:
        if key in item:
            out[key] = item[key][:, source_i, source_j]
    if "flow" in item:
        moves = item["flow"]
        voxels = np.array(moves["voxels"], copy=True)
        voxels[..., :2] = _moved_voxels(matrix, voxels[..., :2], grid.shape[:2])
        transforms = np.asarray(moves["transforms"])
        out["flow"] = dict(moves, voxels=voxels, transforms=(t @ transforms @ t.T).astype(transforms.dtype))
    return out


def _moved_voxels(matrix: np.ndarray, ij: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Voxel indices ij int [..., 2] → their indices after ``matrix`` acts on the voxel centres (a grid centred on 0:
    centre offset i - (n - 1) / 2, in half-voxels to stay integer)."""
    n = np.asarray(shape, np.int64)
    doubled = 2 * ij - (n - 1)                                   # 2 · (i - (n - 1) / 2)
    return ((doubled @ matrix.T) + (n - 1)) // 2


def _source_voxels(matrix: np.ndarray, shape: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Index tensors long [X, Y] (i, j): the old voxel each new voxel (i', j') takes its value from (matrix⁻¹ =
    matrixᵀ for a signed permutation)."""
    i, j = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    source = _moved_voxels(matrix.T, np.stack([i, j], axis=-1), shape)
    return torch.from_numpy(source[..., 0]), torch.from_numpy(source[..., 1])


@dataclass(frozen=True)
class ImageAug:
    """Per-camera affine maps of pixel coordinates, stored image → augmented image: ``maps`` float64 [V, 3, 3]
    (last rows 0 0 1; see the module docstring)."""

    maps: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, height: int, width: int, cameras: int) -> "ImageAug":
        """Maps for ``cameras`` images of ``height`` × ``width`` pixels from ``rng`` (four draws per camera, always:
        scale, sideways shift, flip, angle)."""
        u = rng.random((cameras, 4))
        maps = []
        for scale_u, shift_u, flip_u, angle_u in u:
            s = SCALE_RANGE[0] + scale_u * (SCALE_RANGE[1] - SCALE_RANGE[0])
            shift = (2.0 * shift_u - 1.0) * abs(s - 1.0) * width / 2.0
            angle = np.deg2rad((2.0 * angle_u - 1.0) * ROTATION_DEG)
            maps.append(cls.map_for(height, width, s, shift, bool(flip_u < IMAGE_FLIP_RATIO), angle))
        return cls(np.stack(maps))

    @staticmethod
    def map_for(height: int, width: int, scale: float = 1.0, shift: float = 0.0, flip: bool = False,
                angle: float = 0.0) -> np.ndarray:
        """A = R · F · S (float64 [3, 3]): S scales by ``scale`` about the bottom centre ((W - 1) / 2, H - 0.5) and
        moves the result ``shift`` pixels right; F mirrors x ↦ W - 1 - x when ``flip``; R rotates by ``angle``
        radians about the image centre ((W - 1) / 2, (H - 1) / 2)."""
        cx, bottom, cy = (width - 1) / 2.0, height - 0.5, (height - 1) / 2.0
        s_map = np.array([[scale, 0.0, (1.0 - scale) * cx + shift], [0.0, scale, (1.0 - scale) * bottom],
                          [0.0, 0.0, 1.0]])
        f_map = np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) if flip else np.eye(3)
        c, sn = np.cos(angle), np.sin(angle)
        r_map = np.array([[c, -sn, cx - c * cx + sn * cy], [sn, c, cy - sn * cx - c * cy], [0.0, 0.0, 1.0]])
        return r_map @ f_map @ s_map

    def apply(self, item: dict) -> dict:
        """A copy of the training ``item`` with ``images`` (uint8 [V, H, W, 3]) warped and ``intrinsics`` ([V, 3, 3])
        multiplied by the maps."""
        images = item["images"]
        v, h, w, _ = images.shape
        if self.maps.shape != (v, 3, 3):
            raise ValueError(f"ImageAug has {self.maps.shape[0]} maps for {v} images")
        out = dict(item)
        out["images"] = warp_images(images, np.linalg.inv(self.maps))
        maps = torch.from_numpy(self.maps).to(torch.float64)
        out["intrinsics"] = (maps @ item["intrinsics"].to(torch.float64)).to(item["intrinsics"].dtype)
        return out


def warp_images(images: torch.Tensor, inverse_maps: np.ndarray) -> torch.Tensor:
    """uint8 images [V, H, W, 3] → uint8 [V, H, W, 3]: output pixel q is the bilinear sample of its image at
    ``inverse_maps[v] @ q`` (float [V, 3, 3], pixel-centre coordinates, last rows 0 0 1), 0 outside the image."""
    v, h, w, _ = images.shape
    m = torch.from_numpy(np.asarray(inverse_maps)[:, :2]).to(torch.float32)          # [V, 2, 3]
    xs = torch.arange(w, dtype=torch.float32)[None, None, :]                         # [1, 1, W]
    ys = torch.arange(h, dtype=torch.float32)[None, :, None]                         # [1, H, 1]
    size = torch.tensor([w, h], dtype=torch.float32)
    src = [m[:, r, 0, None, None] * xs + m[:, r, 1, None, None] * ys + m[:, r, 2, None, None] for r in range(2)]
    grid = (2.0 * torch.stack(src, dim=-1) + 1.0) / size - 1.0                       # [V, H, W, 2], align_corners=False
    warped = torch.nn.functional.grid_sample(images.permute(0, 3, 1, 2).to(torch.float32), grid, mode="bilinear",
                                             padding_mode="zeros", align_corners=False)
    return warped.round_().clamp_(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()


@dataclass(frozen=True)
class Photometric:
    """Per-camera photometric jitter: ``brightness`` (added, uint8 levels), ``contrast`` and ``saturation`` (factors),
    each float64 [V]; 0, 1 and 1 leave an image as it is."""

    brightness: np.ndarray
    contrast: np.ndarray
    saturation: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, cameras: int) -> "Photometric":
        """Jitter for ``cameras`` images from ``rng`` (six draws per camera, always: whether and how much of each
        part); each part is applied with probability :data:`PHOTOMETRIC_RATIO`, uniform in its range."""
        u = rng.random((cameras, 6))
        on = u[:, :3] < PHOTOMETRIC_RATIO

        def uniform(bounds, x):
            return bounds[0] + x * (bounds[1] - bounds[0])

        return cls(np.where(on[:, 0], uniform((-BRIGHTNESS_DELTA, BRIGHTNESS_DELTA), u[:, 3]), 0.0),
                   np.where(on[:, 1], uniform(CONTRAST_RANGE, u[:, 4]), 1.0),
                   np.where(on[:, 2], uniform(SATURATION_RANGE, u[:, 5]), 1.0))

    def apply(self, item: dict) -> dict:
        """A copy of the training ``item`` with ``images`` (uint8 [V, H, W, 3], RGB) jittered: x + brightness, then
        × contrast, then grey + saturation · (x - grey) with grey the BT.601 luma, each result clipped to [0, 255],
        rounded to uint8 at the end. Nothing else changes."""
        images = item["images"]
        v = images.shape[0]
        if self.brightness.shape != (v,):
            raise ValueError(f"Photometric has {self.brightness.shape[0]} draws for {v} images")

        def per_camera(values):
            return torch.from_numpy(np.asarray(values, np.float32)).view(v, 1, 1, 1)

        x = (images.to(torch.float32) + per_camera(self.brightness)).clamp_(0, 255)
        x = (x * per_camera(self.contrast)).clamp_(0, 255)
        grey = (x * torch.tensor(GREY_WEIGHTS, dtype=torch.float32)).sum(dim=-1, keepdim=True)
        x = (grey + per_camera(self.saturation) * (x - grey)).clamp_(0, 255)
        out = dict(item)
        out["images"] = x.round_().to(torch.uint8)
        return out
