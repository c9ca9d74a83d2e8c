"""Box tracks of one scene: each annotated instance's box at its keyframes, the box at any time in between, and which
box a point lies in.

nuScenes annotates boxes at keyframes only (``sample_annotation``: global frame, centre, (w, l, h), rotation); a
sweep between two keyframes takes the box interpolated linearly (centre, size) and by slerp (rotation) between the
two annotations of the instance around it. Box frame: x along the length (heading), y along the width, z up, origin
at the box centre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.data.index import SampleIndex
from occflownet.geometry import make_transform, slerp


@dataclass(frozen=True)
class BoxesAt:
    """The boxes present at one time. M boxes; ``instance`` indexes ``BoxTracks``."""

    instance: np.ndarray    # int64 [M]
    box2global: np.ndarray  # float64 [M, 4, 4]
    half: np.ndarray        # float64 [M, 3] half extents along box x, y, z = (l, w, h) / 2

    def __len__(self) -> int:
        return len(self.instance)


@dataclass(frozen=True)
class BoxTracks:
    """Every instance of a scene: I instances, each with its annotations in time order."""

    tokens: tuple[str, ...]            # instance tokens [I]
    labels: np.ndarray                 # uint8 [I] Occ3D class of the instance's category
    times: tuple[np.ndarray, ...]      # per instance int64 [n] µs (the keyframe timestamps)
    centers: tuple[np.ndarray, ...]    # per instance float64 [n, 3] global
    rotations: tuple[np.ndarray, ...]  # per instance float64 [n, 4] (w, x, y, z) box → global
    sizes: tuple[np.ndarray, ...]      # per instance float64 [n, 3] (w, l, h)

    def __len__(self) -> int:
        return len(self.tokens)

    @staticmethod
    def from_index(index: SampleIndex, start: int, stop: int) -> "BoxTracks":
        """The tracks of the keyframes at positions [start, stop) of ``index`` (one scene)."""
        rows: dict[str, list] = {}
        labels: dict[str, int] = {}
        for p in range(start, stop):
            boxes, t = index.boxes(p), int(index.arrays["sample_timestamp"][p])
            for b, token in enumerate(boxes.instance_tokens):
                rows.setdefault(str(token), []).append(
                    (t, boxes.translations[b], boxes.rotations[b], boxes.sizes[b]))
                labels[str(token)] = int(boxes.labels[b])
        tokens = tuple(rows)
        cols = [sorted(rows[k], key=lambda r: r[0]) for k in tokens]
        return BoxTracks(tokens=tokens, labels=np.array([labels[k] for k in tokens], np.uint8),
                         times=tuple(np.array([r[0] for r in c], np.int64) for c in cols),
                         centers=tuple(np.array([r[1] for r in c], np.float64).reshape(-1, 3) for c in cols),
                         rotations=tuple(np.array([r[2] for r in c], np.float64).reshape(-1, 4) for c in cols),
                         sizes=tuple(np.array([r[3] for r in c], np.float64).reshape(-1, 3) for c in cols))

    def at(self, time_us: int, gap_s: float = 0.0) -> BoxesAt:
        """Boxes at ``time_us``: interpolated between the two annotations around it; before the first or after the
        last annotation, that annotation's box when it is at most ``gap_s`` away, else the instance is absent."""
        inst, poses, halves = [], [], []
        gap = gap_s * 1e6
        for i, times in enumerate(self.times):
            j = int(np.searchsorted(times, time_us))
            if j < len(times) and times[j] == time_us:
                a, b, alpha = j, j, 0.0
            elif 0 < j < len(times):
                a, b = j - 1, j
                alpha = (time_us - times[a]) / (times[b] - times[a])
            elif (j == 0 and times[0] - time_us <= gap) or (j == len(times) and time_us - times[-1] <= gap):
                a = b = min(j, len(times) - 1)
                alpha = 0.0
            else:
                continue
            c = self.centers[i][a] + alpha * (self.centers[i][b] - self.centers[i][a])
            q = slerp(self.rotations[i][a], self.rotations[i][b], alpha)
            wlh = self.sizes[i][a] + alpha * (self.sizes[i][b] - self.sizes[i][a])
            inst.append(i)
            poses.append(make_transform(q, c))
            halves.append(wlh[[1, 0, 2]] / 2.0)
        return BoxesAt(np.array(inst, np.int64), np.array(poses, np.float64).reshape(-1, 4, 4),
                       np.array(halves, np.float64).reshape(-1, 3))


def points_in_boxes(points: np.ndarray, boxes: BoxesAt, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Which box each point lies in, and where in it.

    points float64 [N, 3] global; a point is in box m when its box-frame coordinates lie within the box grown by
    ``margin`` on every side. Returns (box int64 [N]: position in ``boxes`` or -1; local float64 [N, 3]: box-frame
    coordinates, 0 where box is -1). A point in several boxes takes the one whose centre is nearest."""
    from scipy.spatial import cKDTree

    n = len(points)
    which = np.full(n, -1, np.int64)
    local = np.zeros((n, 3))
    if n == 0 or len(boxes) == 0:
        return which, local
    tree = cKDTree(points[:, :2])
    best = np.full(n, np.inf)
    for m in range(len(boxes)):
        T, reach = boxes.box2global[m], boxes.half[m] + margin
        cand = np.asarray(tree.query_ball_point(T[:2, 3], float(np.hypot(reach[0], reach[1]))), np.int64)
        if len(cand) == 0:
            continue
        p = (points[cand] - T[:3, 3]) @ T[:3, :3]          # R^T (p - c)
        dist = np.linalg.norm(p, axis=1)
        take = np.all(np.abs(p) <= reach, axis=1) & (dist < best[cand])
        idx = cand[take]
        which[idx], local[idx], best[idx] = m, p[take], dist[take]
    return which, local
