"""Colours of surfaces: procedural textures (asphalt, pavers, grass, facades, foliage, glass, stripes), Lambert
shading under a sun, distance haze and a sky with clouds. Pure numpy on flat arrays of hit points.

All colours are RGB floats in [0, 1]. Coordinates for textures are metres (ground: scene frame, boxes: box frame)
so patterns keep their size on screen as the ego moves.
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import DRIVEABLE_SURFACE, OTHER_FLAT, SIDEWALK, TERRAIN
from occflownet.synth.materials import (GROUND_COLOR, PAINT_COLOR, TEX_BUS, TEX_DARK, TEX_FACADE, TEX_FOLIAGE,
                                        TEX_GLASS, TEX_STRIPES)

SKY_ZENITH = np.array([0.32, 0.52, 0.86], np.float32)
SKY_HORIZON = np.array([0.78, 0.85, 0.93], np.float32)
WINDOW = np.array([0.18, 0.24, 0.33], np.float32)


def hash2(i: np.ndarray, j: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice cell (i, j) (float arrays of integers)."""
    v = np.sin(i * 127.1 + j * 311.7 + seed * 74.7) * 43758.5453
    return (v - np.floor(v)).astype(np.float32)


def value_noise(x: np.ndarray, y: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth noise in [0, 1): bilinear interpolation of ``hash2`` on the unit lattice."""
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = (x - ix).astype(np.float32), (y - iy).astype(np.float32)
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    a, b = hash2(ix, iy, seed), hash2(ix + 1, iy, seed)
    c, d = hash2(ix, iy + 1, seed), hash2(ix + 1, iy + 1, seed)
    return (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy


def lambert(normal: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Light factor [M] for unit normals [M, 3]: ambient + sun + a little sky light from above."""
    return (0.48 + 0.55 * np.clip(normal @ sun, 0, None) + 0.08 * normal[:, 2]).astype(np.float32)


def ground_color(cls: np.ndarray, paint: np.ndarray, xy_scene: np.ndarray) -> np.ndarray:
    """Colour [M, 3] of ground points of Occ3D class ``cls`` [M] with ``paint`` [M] at scene (x, y) [M, 2]."""
    x, y = xy_scene[:, 0], xy_scene[:, 1]
    base = GROUND_COLOR[cls].copy()
    mult = np.ones(len(cls), np.float32)
    fine = hash2(np.floor(x * 5), np.floor(y * 5), 3)
    broad = value_noise(x * 0.15, y * 0.15, 7)
    road = cls == DRIVEABLE_SURFACE
    mult[road] = 0.9 + 0.12 * fine[road] + 0.12 * broad[road]
    walk = cls == SIDEWALK
    joints = (np.abs(x - np.round(x)) < 0.03) | (np.abs(y * 2 - np.round(y * 2)) < 0.06)
    mult[walk] = np.where(joints[walk], 0.78, 0.95 + 0.08 * hash2(np.floor(x), np.floor(y * 2), 5)[walk])
    grass = cls == TERRAIN
    mult[grass] = 0.7 + 0.3 * fine[grass] + 0.35 * broad[grass]
    flat = cls == OTHER_FLAT
    checker = (np.floor(x * 2) + np.floor(y * 2)) % 2
    mult[flat] = 0.92 + 0.1 * checker[flat] + 0.05 * fine[flat]
    col = base * mult[:, None]
    painted = paint > 0
    col[painted] = PAINT_COLOR[paint[painted]] * (0.92 + 0.08 * fine[painted, None])
    return col


def box_color(base: np.ndarray, texture: np.ndarray, local: np.ndarray, half: np.ndarray, axis: np.ndarray,
              box_id: np.ndarray) -> np.ndarray:
    """Colour [M, 3] of box surface points: ``base`` [M, 3], ``texture`` [M] kinds, ``local`` [M, 3] point in the
    box frame, ``half`` [M, 3] box half extents, ``axis`` [M] face axis (0/1 sides, 2 top/bottom)."""
    col = base.astype(np.float32).copy()
    height = local[:, 2] + half[:, 2]  # above the box bottom
    along = np.where(axis == 0, local[:, 1], local[:, 0])  # horizontal coordinate on the face
    side = axis < 2
    t = texture
    sel = (t == TEX_FACADE) & side
    if sel.any():
        per = 2.2 + 1.4 * hash2(box_id[sel].astype(np.float64), 1.0, 11)
        floor_h = 2.9 + 0.6 * hash2(box_id[sel].astype(np.float64), 2.0, 11)
        u = (along[sel] + half[sel, 0] * 3.1) / per
        v = height[sel] / floor_h
        fu, fv = u - np.floor(u), v - np.floor(v)
        win = (fu > 0.22) & (fu < 0.78) & (fv > 0.3) & (fv < 0.82) & (height[sel] > 1.2)
        shade = 0.8 + 0.45 * hash2(np.floor(u), np.floor(v), 13)[:, None]
        c = col[sel]
        c[win] = WINDOW * shade[win]
        col[sel] = c * np.where(win[:, None], 1.0, 0.92 + 0.1 * hash2(np.floor(u * 4), np.floor(v * 8), 2)[:, None])
    sel = t == TEX_FOLIAGE
    if sel.any():
        p = local[sel]
        n = hash2(np.floor(p[:, 0] * 4 + p[:, 2] * 3), np.floor(p[:, 1] * 4 - p[:, 2] * 3), 17)
        col[sel] *= (0.65 + 0.55 * n)[:, None]
    sel = t == TEX_GLASS
    if sel.any():
        col[sel] *= (0.8 + 0.5 * height[sel] / np.maximum(2 * half[sel, 2], 1e-3))[:, None]
    sel = t == TEX_STRIPES
    if sel.any():
        band = ((height[sel] / 0.25).astype(np.int64) % 2) == 1
        col[sel] = np.where(band[:, None], np.float32(0.95), col[sel])
    sel = (t == TEX_BUS) & side
    if sel.any():
        h = height[sel] / np.maximum(2 * half[sel, 2], 1e-3)
        pillar = np.abs((along[sel] / 1.3) - np.round(along[sel] / 1.3)) < 0.08
        win = (h > 0.45) & (h < 0.82) & ~pillar
        col[sel] = np.where(win[:, None], WINDOW, col[sel])
    sel = t == TEX_DARK
    if sel.any():
        col[sel] *= 0.9
    return col


def sky_color(dirs: np.ndarray, seed: int) -> np.ndarray:
    """Sky colour [M, 3] for unit view directions [M, 3] (global): gradient, soft clouds."""
    el = np.clip(dirs[:, 2], -0.2, 1.0)
    f = np.clip(el * 2.5, 0, 1)[:, None].astype(np.float32)
    col = SKY_HORIZON * (1 - f) + SKY_ZENITH * f
    px, py = dirs[:, 0] / (el + 0.25) * 2.0, dirs[:, 1] / (el + 0.25) * 2.0
    cloud = value_noise(px, py, seed) * 0.6 + value_noise(px * 2.3, py * 2.3, seed + 1) * 0.4
    cloud = np.clip((cloud - 0.55) * 3.0, 0, 1)[:, None] * np.clip(el * 6, 0, 1)[:, None]
    return col * (1 - cloud) + np.float32(0.96) * cloud


def haze(color: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Blend colours [M, 3] towards the horizon colour with distance [M] (m)."""
    f = (1.0 - np.exp(-distance / 350.0)).astype(np.float32)[:, None]
    return color * (1 - f) + SKY_HORIZON * f


def shadow_raster(boxes_scene_corners: np.ndarray, sun_scene: np.ndarray, x0: float, y0: float, shape,
                  res: float = 0.2) -> np.ndarray:
    """Sun shadows of boxes on the ground (z = 0): uint8 [NX, NY], 1 where shadowed, cell (i, j) at
    (x0 + i*res, y0 + j*res) in the scene frame. ``boxes_scene_corners`` [N, 8, 3] scene frame; ``sun_scene`` [3]
    unit vector towards the sun. Shadows only darken the ground's colour; they are not geometry."""
    import cv2

    out = np.zeros((shape[1], shape[0]), np.uint8)  # cv2 draws (x = column, y = row): store as [NY, NX]
    if sun_scene[2] <= 0.05 or len(boxes_scene_corners) == 0:
        return out.T
    c = boxes_scene_corners
    flat = c[..., :2] - c[..., 2:3] * (sun_scene[:2] / sun_scene[2])  # follow the sun ray down to z = 0
    pix = np.round((flat - [x0, y0]) / res * 4).astype(np.int32)  # 2 bits of sub-pixel precision
    for poly in pix:
        hull = cv2.convexHull(poly)
        cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=2)
    return out.T
