"""Line of sight through object boxes: which rays pass through an annotated 3D box before reaching their point.

A camera ray is made from a LiDAR point projected into a camera (``data/rays.py``). The camera sits about a metre
from the LiDAR and sees at its own timestamp, so the point can be hidden from it by an object the LiDAR saw past
(parallax), and a ray of a temporal frame t ≠ 0 can cross the place where an object stands at the current
keyframe (it moved). Such a ray tells the renderer "free" through voxels the labels call occupied. On the fitting
world 2–4 % of the t = 0 rays pass more than a metre through a labelled car before their point, and the rays of
the six temporal frames crossing a car of the keyframe outnumber the rays that end on cars three to one
(docs/data.md). Dropping them (``RayConfig.box_line_of_sight``, beyond the paper) is a data-side filter: it
needs the boxes, not the model's predicted classes, as the official dynamic filter does.

Frames: rays and boxes in one ego frame (the current keyframe's). Boxes are ``EgoBoxes`` (centre, nuScenes
``wlh`` size, rotation box → ego).
"""
from __future__ import annotations

import numpy as np

from occflownet.data.records import EgoBoxes

MARGIN = 0.2  # metres added to each face of a box: half a 0.4 m voxel, the labels' resolution
FAR = 1000.0  # metres: where an unbounded segment (a free ray) is cut for culling; far beyond any grid


def segment_box_hits(origins: np.ndarray, directions: np.ndarray, lengths: np.ndarray, boxes: EgoBoxes,
                     margin: float = MARGIN) -> list[np.ndarray]:
    """For each box b, the indices (int64, ascending) of the segments ``origins[r] + s · directions[r]``,
    0 ≤ s ≤ ``lengths[r]``, that meet box b grown by ``margin`` metres per face (slab test in the box frame).

    origins [R, 3], directions [R, 3] (unit or not: ``s`` is in units of their length), lengths [R] ≥ 0 (inf: a
    half-line)."""
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
    half = boxes.sizes[:, [1, 0, 2]] / 2.0 + margin                      # (l, w, h) / 2 along box x, y, z
    # Cull first: only segments whose axis-aligned bounds overlap the box's take the slab test. An infinite
    # segment is bounded at FAR metres, beyond which no box near the grid lies.
    ends = origins + np.minimum(lengths, FAR)[:, None] * directions
    seg_lo, seg_hi = np.minimum(origins, ends), np.maximum(origins, ends)
    box_reach = np.einsum("bij,bj->bi", np.abs(boxes.rotations), half)  # half extent of each box's bounds
    out = []
    for b in range(len(boxes)):
        lo_b, hi_b = boxes.centers[b] - box_reach[b], boxes.centers[b] + box_reach[b]
        near = np.flatnonzero((seg_lo[:, 0] <= hi_b[0]) & (seg_hi[:, 0] >= lo_b[0])
                              & (seg_lo[:, 1] <= hi_b[1]) & (seg_hi[:, 1] >= lo_b[1])
                              & (seg_lo[:, 2] <= hi_b[2]) & (seg_hi[:, 2] >= lo_b[2]))
        if len(near) == 0:
            out.append(near)
            continue
        R = boxes.rotations[b]
        o = (origins[near] - boxes.centers[b]) @ R                        # R^T (p - c), per row
        d = directions[near] @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half[b] - o) / d
            t2 = (half[b] - o) / d
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        # a direction parallel to a slab: inside it for every s (o within the slab) or never
        parallel = d == 0
        inside_slab = np.abs(o) <= half[b]
        lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), lo)
        hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), hi)
        enter, leave = lo.max(axis=1), hi.min(axis=1)
        out.append(near[(enter <= leave) & (leave >= 0.0) & (enter <= lengths[near])])
    return out


def blocked_by_boxes(origins: np.ndarray, directions: np.ndarray, lengths: np.ndarray, boxes: EgoBoxes,
                     margin: float = MARGIN) -> np.ndarray:
    """bool [R]: rays whose segment to their point passes through a box (grown by ``margin``) that does not hold
    the point itself. A ray that ends on an object (its point inside that object's box) is not blocked by it.
    Rays to no point (free rays) take ``lengths = inf``: any box on their way blocks them."""
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
    blocked = np.zeros(len(lengths), dtype=bool)
    if len(boxes) == 0 or len(lengths) == 0:
        return blocked
    for b, hit in enumerate(segment_box_hits(origins, directions, lengths, boxes, margin)):
        hit = hit[~blocked[hit]]
        finite = hit[np.isfinite(lengths[hit])]
        ends = origins[finite] + lengths[finite, None] * directions[finite]
        holds_end = np.zeros(len(lengths), dtype=bool)
        holds_end[finite] = boxes.take([b]).contains(ends, margin)[0]
        blocked[hit[~holds_end[hit]]] = True
    return blocked
