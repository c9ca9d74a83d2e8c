"""Camera images by ray casting: one ray per pixel through the world's boxes and ground, then shading.

Pixel convention: pixel (row r, col c) is the ray through image point (u, v) = (c + 0.5, r + 0.5), i.e. a
projected point (u, v) lands in pixel (floor(v), floor(u)); with the rig's principal point (W/2, H/2) this is the
continuous image coordinate system of nuScenes' intrinsics. Depth is z-depth in the OpenCV camera frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import FREE
from occflownet.synth.raycast import Block, box_faces, boxes_in_range, cast_blocks, ground_t
from occflownet.synth.shading import box_color, ground_color, haze, lambert, shadow_raster, sky_color
from occflownet.synth.world import Boxes, World

NEAR = 0.05
FAR = 250.0
_EDGES = [(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit]


@dataclass
class CameraRender:
    """One rendered camera image. ``rgb`` uint8 [H, W, 3]; ``depth`` float32 [H, W] z-depth in metres (inf: sky);
    ``occ`` uint8 [H, W] Occ3D class of the visible surface (17 = sky); ``box`` int32 [H, W] index of the visible
    box in the frame's ``Boxes`` (-1: ground or sky); ``visible`` / ``alone`` int64 [N boxes]: pixels where each
    box is visible / would be hit if nothing occluded it."""

    rgb: np.ndarray
    depth: np.ndarray
    occ: np.ndarray
    box: np.ndarray
    visible: np.ndarray
    alone: np.ndarray


def pixel_dirs(K: np.ndarray, cam2global: np.ndarray, width: int, height: int) -> np.ndarray:
    """Global-frame ray directions [H, W, 3] through pixel centres, scaled so that their camera z is 1."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    K = np.asarray(K, dtype=np.float64)
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    return d_cam @ np.asarray(cam2global)[:3, :3].T


def camera_blocks(boxes: Boxes, K: np.ndarray, cam2global: np.ndarray, width: int, height: int,
                  far: float = FAR) -> list[Block]:
    """The pixel rectangle each box can cover (corners projected; edges clipped at the near plane)."""
    origin = cam2global[:3, 3]
    idx = boxes_in_range(boxes, origin, far)
    if len(idx) == 0:
        return []
    corners = boxes.subset(idx).corners()  # [n, 8, 3] global
    R = cam2global[:3, :3]
    pc = (corners - origin) @ R  # camera frame: p_cam = R^T (p - o)
    blocks = []
    for n, i in enumerate(idx):
        p = pc[n]
        z = p[:, 2]
        if (z < NEAR).all():
            continue
        if (z < NEAR).any():
            pts = [p[z >= NEAR]]
            for a, b in _EDGES:
                if (z[a] < NEAR) != (z[b] < NEAR):
                    f = (NEAR - z[a]) / (z[b] - z[a])
                    pts.append((p[a] + f * (p[b] - p[a]))[None])
            p = np.concatenate(pts)
        u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 1] * p[:, 1] / p[:, 2] + K[0, 2]
        v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        c0, c1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 1, width)
        r0, r1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 1, height)
        if c0 < c1 and r0 < r1:
            blocks.append(Block(int(i), r0, r1, c0, c1))
    return blocks


def render_camera(world: World, boxes: Boxes, K: np.ndarray, cam2global: np.ndarray, width: int, height: int,
                  rng: np.random.Generator | None = None, far: float = FAR) -> CameraRender:
    """Render one camera. ``boxes``: the world's geometry at this camera's timestamp (global frame);
    ``K`` [3, 3] intrinsics for ``width × height``; ``cam2global`` [4, 4] (OpenCV camera → global).
    ``rng`` adds slight sensor noise (none if omitted)."""
    K = np.asarray(K, dtype=np.float64)
    cam2global = np.asarray(cam2global, dtype=np.float64)
    origin = cam2global[:3, 3]
    dirs = pixel_dirs(K, cam2global, width, height)
    t_buf = np.full((height, width), np.inf)
    id_buf = np.full((height, width), -1, np.int32)
    alone = np.zeros(len(boxes), np.int64)
    cast_blocks(origin, dirs, boxes, camera_blocks(boxes, K, cam2global, width, height, far), t_buf, id_buf, alone)
    tg = ground_t(origin, dirs)
    ground = (tg < t_buf) & (tg < far)
    t_buf[ground] = tg[ground]
    id_buf[ground] = -1
    sky = ~np.isfinite(t_buf) | (t_buf > far)
    t_buf[sky] = np.inf

    rgb = np.zeros((height, width, 3), np.float32)
    occ = np.full((height, width), FREE, np.uint8)
    flat_dirs = dirs.reshape(-1, 3)
    norm = np.linalg.norm(flat_dirs, axis=1)
    t, ids = t_buf.reshape(-1), id_buf.reshape(-1)
    col, occ_f = rgb.reshape(-1, 3), occ.reshape(-1)

    g = np.nonzero(ground.reshape(-1) & ~sky.reshape(-1))[0]
    if len(g):
        p = origin + t[g, None] * flat_dirs[g]
        cls, paint = world.ground_lookup_global(p[:, :2])
        s2g = world.scene2global
        xy_scene = (p[:, :2] - s2g[:2, 3]) @ s2g[:2, :2]
        light = np.full(len(g), 0.48 + 0.55 * max(world.sun[2], 0) + 0.08, np.float32)
        light[in_shadow(world, boxes, xy_scene)] = 0.56
        c = ground_color(cls, paint, xy_scene) * light[:, None]
        col[g] = haze(c, t[g] * norm[g])
        occ_f[g] = cls
    b = np.nonzero(ids >= 0)[0]
    if len(b):
        bid = ids[b]
        p = origin + t[b, None] * flat_dirs[b]
        normal, local, axis = box_faces(boxes, bid, p)
        c = box_color(boxes.color[bid], boxes.texture[bid], local, boxes.half[bid], axis, bid)
        c *= lambert(normal, world.sun)[:, None]
        col[b] = haze(c, t[b] * norm[b])
        occ_f[b] = boxes.occ[bid]
    s = np.nonzero(sky.reshape(-1))[0]
    if len(s):
        col[s] = sky_color(flat_dirs[s] / norm[s, None], world.sky_seed)
    if rng is not None:
        rgb += rng.normal(0.0, 0.012, rgb.shape).astype(np.float32)
    visible = np.bincount(id_buf[id_buf >= 0], minlength=len(boxes)).astype(np.int64)
    return CameraRender(rgb=(np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), depth=t_buf.astype(np.float32),
                        occ=occ, box=id_buf, visible=visible, alone=alone)


SHADOW_RES = 0.2


def in_shadow(world: World, boxes: Boxes, xy_scene: np.ndarray) -> np.ndarray:
    """Whether ground points at scene (x, y) [M, 2] lie in the sun shadow of ``boxes`` (global frame)."""
    g2s = np.linalg.inv(world.scene2global)
    sun = g2s[:3, :3] @ world.sun
    x0, x1 = world.meta["extent_x"]
    y0, y1 = world.meta["extent_y"]
    shape = (int(np.ceil((x1 - x0) / SHADOW_RES)), int(np.ceil((y1 - y0) / SHADOW_RES)))
    corners = boxes.transformed(g2s).corners()
    raster = shadow_raster(corners, sun, x0, y0, shape, SHADOW_RES)
    i = np.floor((xy_scene[:, 0] - x0) / SHADOW_RES).astype(np.int64)
    j = np.floor((xy_scene[:, 1] - y0) / SHADOW_RES).astype(np.int64)
    ok = (i >= 0) & (i < shape[0]) & (j >= 0) & (j < shape[1])
    out = np.zeros(len(i), bool)
    out[ok] = raster[i[ok], j[ok]] > 0
    return out


def cast_rays(boxes: Boxes, origin: np.ndarray, dirs: np.ndarray, far: float = FAR) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of arbitrary rays [M, 3] from ``origin`` [3] (global) against every box in range and the ground,
    with no screen-space culling: (t [M] in units of ``dirs``, inf for none; box index [M], -1 ground/none).
    The reference the culled renderer must agree with; also used to cast rays through exact sub-pixel points."""
    dirs = np.asarray(dirs, dtype=np.float64).reshape(1, -1, 3)
    t_buf = np.full(dirs.shape[:2], np.inf)
    id_buf = np.full(dirs.shape[:2], -1, np.int32)
    blocks = [Block(int(i), 0, 1, 0, dirs.shape[1]) for i in boxes_in_range(boxes, origin, far)]
    cast_blocks(np.asarray(origin, dtype=np.float64), dirs, boxes, blocks, t_buf, id_buf)
    tg = ground_t(origin, dirs)
    ground = (tg < t_buf) & (tg < far)
    t_buf[ground], id_buf[ground] = tg[ground], -1
    t_buf[t_buf > far] = np.inf
    return t_buf[0], id_buf[0]
