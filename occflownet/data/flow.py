"""Precomputed occupancy flow of dynamic boxes, one compact record per keyframe (numpy only, no torch).

``box_flows`` turns the 3D boxes of a keyframe and of its temporal frames (same scene) into a ``FlowRecord``: for
each dynamic box (class in ``occ3d.DYNAMIC_CLASSES``, centre inside the grid range) and each frame t ≠ 0 where
the same instance is annotated, the rigid transform T_box(t) · T_box(0)⁻¹ expressed in the *current ego frame*
(the ego pose at the keyframe's LiDAR timestamp). Only the box pose at time 0 and the 4×4 transforms are stored;
the voxels are derived at training time by ``flow_moves`` (``voxels_in_box`` of the enlarged box), so a record
takes a few KB instead of the official ~260 KB of voxel lists per keyframe.

Box input (plain arrays, per frame, global frame): a mapping with
  ``instance_token`` [N] str, ``label`` int [N] (Occ3D class, e.g. ``occ3d.category_to_occ3d(category_name)``),
  ``center`` float [N, 3] (metres), ``size_wlh`` float [N, 3] (nuScenes w, l, h), ``rotation`` float [N, 4]
  (quaternion (w, x, y, z), box → global). ``boxes_from_annotations`` builds it from nuScenes annotation records.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from ..occ3d import DYNAMIC_CLASSES, GRID, Grid, category_to_occ3d
from ..files import atomic_path
from ..worker_processes import spawn_context
from ..geometry import invert, make_transform, matrix_to_quaternion
from .box_voxels import MARGIN_ADD, MARGIN_SCALE, voxels_in_box

FLOW_FORMAT_VERSION = 1
_BOX_KEYS = ("instance_token", "label", "center", "size_wlh", "rotation")


@dataclass
class FlowRecord:
    """Flow of one keyframe. Frame: ego frame of the keyframe (ego pose at its LiDAR timestamp).

    Box table (dynamic boxes with at least one match), rows b:
      box_index int32 [Nb] (position of the box in the keyframe's input boxes), label uint8 [Nb] (Occ3D class),
      center float32 [Nb, 3], size_wlh float32 [Nb, 3] (nuScenes w, l, h, not enlarged),
      rotation float32 [Nb, 4] (quaternion (w, x, y, z), box → current ego frame).
    Move table, rows k: offset int8 [K] (t, in keyframes, ≠ 0), move_box int16 [K] (row of the box table),
      transform float32 [K, 4, 4] (ego→ego: a point of the box at time 0 → its place at time t).
    """

    sample_token: str
    box_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    label: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    size_wlh: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    rotation: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    move_box: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int16))
    transform: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4), np.float32))
    version: int = FLOW_FORMAT_VERSION

    def __post_init__(self):
        self.box_index = np.asarray(self.box_index, np.int32).reshape(-1)
        self.label = np.asarray(self.label, np.uint8).reshape(-1)
        self.center = np.asarray(self.center, np.float32).reshape(-1, 3)
        self.size_wlh = np.asarray(self.size_wlh, np.float32).reshape(-1, 3)
        self.rotation = np.asarray(self.rotation, np.float32).reshape(-1, 4)
        self.offset = np.asarray(self.offset, np.int8).reshape(-1)
        self.move_box = np.asarray(self.move_box, np.int16).reshape(-1)
        self.transform = np.asarray(self.transform, np.float32).reshape(-1, 4, 4)
        nb, k = len(self.box_index), len(self.offset)
        for name in ("label", "center", "size_wlh", "rotation"):
            if len(getattr(self, name)) != nb:
                raise ValueError(f"FlowRecord {self.sample_token}: {name} has {len(getattr(self, name))} rows, "
                                 f"box_index {nb}")
        for name in ("move_box", "transform"):
            if len(getattr(self, name)) != k:
                raise ValueError(f"FlowRecord {self.sample_token}: {name} has {len(getattr(self, name))} rows, "
                                 f"offset {k}")
        if k and (self.move_box.min() < 0 or self.move_box.max() >= nb):
            raise ValueError(f"FlowRecord {self.sample_token}: move_box must index the {nb} boxes")
        if np.any(self.offset == 0):
            raise ValueError(f"FlowRecord {self.sample_token}: offset 0 (the keyframe itself) has no flow")

    @property
    def offsets(self) -> list[int]:
        """The frame offsets t that have at least one move, sorted."""
        return sorted(set(int(t) for t in self.offset))

    def arrays(self) -> dict[str, np.ndarray]:
        return {"box_index": self.box_index, "label": self.label, "center": self.center,
                "size_wlh": self.size_wlh, "rotation": self.rotation, "offset": self.offset,
                "move_box": self.move_box, "transform": self.transform}


def _check_boxes(boxes: Mapping, where: str) -> dict[str, np.ndarray]:
    missing = [k for k in _BOX_KEYS if k not in boxes]
    if missing:
        raise ValueError(f"{where}: box arrays miss {missing} (need {list(_BOX_KEYS)})")
    label = np.asarray(boxes["label"]).reshape(-1)
    if label.size and label.dtype.kind not in "iu":
        raise ValueError(f"{where}: 'label' must hold integer Occ3D classes, got dtype {label.dtype}")
    out = {"instance_token": np.asarray(boxes["instance_token"], dtype=str).reshape(-1),
           "label": label.astype(np.int64),
           "center": np.asarray(boxes["center"], np.float64).reshape(-1, 3),
           "size_wlh": np.asarray(boxes["size_wlh"], np.float64).reshape(-1, 3),
           "rotation": np.asarray(boxes["rotation"], np.float64).reshape(-1, 4)}
    n = len(out["instance_token"])
    for key, value in out.items():
        if len(value) != n:
            raise ValueError(f"{where}: '{key}' has {len(value)} rows but instance_token has {n}")
        if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
            raise ValueError(f"{where}: '{key}' has non-finite values")
    if len(set(out["instance_token"].tolist())) != n:
        raise ValueError(f"{where}: instance_token values must be unique within a frame")
    if n and np.any(np.linalg.norm(out["rotation"], axis=1) < 1e-9):
        raise ValueError(f"{where}: 'rotation' has a zero quaternion")
    return out


def box_poses(boxes: Mapping) -> np.ndarray:
    """Box → global poses float64 [N, 4, 4] from the box arrays (centre, quaternion (w, x, y, z))."""
    b = _check_boxes(boxes, "box_poses")
    poses = [make_transform(q, c) for q, c in zip(b["rotation"], b["center"])]
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def box_flows(sample_token: str, boxes_now: Mapping, boxes_at: Mapping[int, Mapping], ego2global_now,
              dynamic_classes: Sequence[int] = DYNAMIC_CLASSES, grid: Grid = GRID) -> FlowRecord:
    """Flow record of one keyframe.

    boxes_now: the keyframe's boxes (global frame, see module doc); boxes_at: {t: boxes of keyframe t} for the
    temporal frames t ≠ 0 that exist in the same scene (the caller leaves out frames beyond the scene's ends);
    ego2global_now float [4, 4]: ego pose at the keyframe's LiDAR timestamp (defines the current ego frame).
    Boxes kept: class in ``dynamic_classes`` and centre (current ego frame) inside the grid range; a kept box gets
    one move per frame t where its instance token appears. Boxes with no match at any t are left out.
    """
    ego2global = np.asarray(ego2global_now, np.float64)
    if ego2global.shape != (4, 4) or not np.all(np.isfinite(ego2global)):
        raise ValueError(f"{sample_token}: ego2global_now must be a finite 4x4 matrix, got shape {ego2global.shape}")
    global2ego = invert(ego2global)
    now = _check_boxes(boxes_now, f"{sample_token} boxes_now")
    if not now["instance_token"].size:
        return FlowRecord(sample_token)
    pose0 = global2ego @ box_poses(now)  # box → current ego, [N, 4, 4]
    keep = np.isin(now["label"], np.asarray(dynamic_classes)) & grid.contains(pose0[:, :3, 3])
    inv0 = {i: invert(pose0[i]) for i in np.nonzero(keep)[0]}
    moves = []  # (t, input box index, transform)
    for t in sorted(boxes_at):
        if int(t) == 0:
            raise ValueError(f"{sample_token}: boxes_at must not contain t = 0 (the keyframe itself)")
        if not -128 <= int(t) <= 127:
            raise ValueError(f"{sample_token}: frame offset {t} out of range")
        then = _check_boxes(boxes_at[t], f"{sample_token} boxes_at[{t}]")
        row_of = {tok: r for r, tok in enumerate(then["instance_token"].tolist())}
        rows = [(i, row_of[now["instance_token"][i]]) for i in inv0 if now["instance_token"][i] in row_of]
        if not rows:
            continue
        pose_t = global2ego @ box_poses({k: v[[r for _, r in rows]] for k, v in then.items()})
        for (i, _), p in zip(rows, pose_t):
            moves.append((int(t), i, p @ inv0[i]))
    used = sorted({i for _, i, _ in moves})
    if not used:
        return FlowRecord(sample_token)
    row = {i: r for r, i in enumerate(used)}
    return FlowRecord(
        sample_token,
        box_index=np.asarray(used),
        label=now["label"][used],
        center=pose0[used, :3, 3],
        size_wlh=now["size_wlh"][used],
        rotation=np.stack([matrix_to_quaternion(pose0[i, :3, :3]) for i in used]),
        offset=[t for t, _, _ in moves],
        move_box=[row[i] for _, i, _ in moves],
        transform=np.stack([m for _, _, m in moves]),
    )


def box_arrays(boxes) -> dict[str, np.ndarray]:
    """The sample index's global-frame ``Boxes`` (``occflownet.data.records``) → box arrays for ``box_flows``."""
    return {"instance_token": boxes.instance_tokens, "label": boxes.labels, "center": boxes.translations,
            "size_wlh": boxes.sizes, "rotation": boxes.rotations}


def keyframe_flow(index, position: int, horizon: int = 3,
                  dynamic_classes: Sequence[int] = DYNAMIC_CLASSES, grid: Grid = GRID) -> FlowRecord:
    """Flow record of keyframe ``position`` of a ``SampleIndex``: its boxes against those of the keyframes
    t ∈ [-horizon, horizon] \\ {0} of the same scene (``index.neighbours``), in its current ego frame (the ego
    pose at its LiDAR timestamp). This is what ``occflownet prepare`` calls once per keyframe."""
    sample = index[position]
    frames = {t: box_arrays(index[j].boxes) for t, j in index.neighbours(position, horizon) if t != 0}
    return box_flows(sample.token, box_arrays(sample.boxes), frames, sample.ego2global, dynamic_classes, grid)


def boxes_from_annotations(annotations: Iterable[Mapping]) -> dict[str, np.ndarray]:
    """nuScenes ``sample_annotation``-like records → box arrays for ``box_flows``.

    Each record needs ``instance_token``, ``translation`` [3], ``size`` [3] (w, l, h), ``rotation`` [4]
    (w, x, y, z), all global frame, and either ``label`` (Occ3D class) or ``category_name`` (nuScenes name).
    """
    anns = list(annotations)
    labels = []
    for n, a in enumerate(anns):
        for key in ("instance_token", "translation", "size", "rotation"):
            if key not in a:
                raise ValueError(f"annotation {n}: missing '{key}'")
        if "label" in a:
            labels.append(int(a["label"]))
        elif "category_name" in a:
            labels.append(category_to_occ3d(a["category_name"]))
        else:
            raise ValueError(f"annotation {n}: needs 'label' or 'category_name'")
    return {"instance_token": np.asarray([a["instance_token"] for a in anns], dtype=str),
            "label": np.asarray(labels, np.int64),
            "center": np.asarray([a["translation"] for a in anns], np.float64).reshape(-1, 3),
            "size_wlh": np.asarray([a["size"] for a in anns], np.float64).reshape(-1, 3),
            "rotation": np.asarray([a["rotation"] for a in anns], np.float64).reshape(-1, 4)}


def flow_moves(record: FlowRecord, offsets: Sequence[int], margin_scale: float = MARGIN_SCALE,
               margin_add: float = MARGIN_ADD, grid: Grid = GRID) -> dict[str, np.ndarray]:
    """The record's moves into the frames ``offsets`` (the order of the output volumes of one sample), with the
    voxels of each enlarged box at time 0 computed here (once per box, shared by all its moves).

    Returns arrays for ``occflownet.render.occupancy_flow.PackedMoves.from_arrays``: voxels int64 [M, 3],
    box int64 [M] (move row of each voxel), transforms float32 [K, 4, 4], classes int64 [K], volume int64 [K]
    (position of the move's t in ``offsets``). Moves to frames not in ``offsets`` are left out; an offset with no
    moves (or 0) simply gets none.
    """
    position = {int(t): n for n, t in enumerate(offsets)}
    rows = [k for k in range(len(record.offset)) if int(record.offset[k]) in position]
    box_voxels = {}
    voxels, box = [], []
    for j, k in enumerate(rows):
        b = int(record.move_box[k])
        if b not in box_voxels:
            box_voxels[b] = voxels_in_box(record.center[b], record.size_wlh[b], record.rotation[b],
                                          margin_scale, margin_add, grid)
        voxels.append(box_voxels[b])
        box.append(np.full(len(box_voxels[b]), j, np.int64))
    return {"voxels": np.concatenate(voxels) if voxels else np.zeros((0, 3), np.int64),
            "box": np.concatenate(box) if box else np.zeros(0, np.int64),
            "transforms": record.transform[rows].reshape(-1, 4, 4),
            "classes": record.label[record.move_box[rows]].astype(np.int64),
            "volume": np.asarray([position[int(record.offset[k])] for k in rows], np.int64)}


def save_flow_records(path, records: Sequence[FlowRecord]) -> None:
    """Write many records (e.g. one split) into one ``.npz``: the tables concatenated, with row offsets."""
    recs = list(records)
    tokens = [r.sample_token for r in recs]
    if len(set(tokens)) != len(tokens):
        raise ValueError(f"{path}: sample tokens must be unique across the records written together")
    tables = {key: np.concatenate([r.arrays()[key] for r in recs]) if recs else FlowRecord("").arrays()[key]
              for key in FlowRecord("").arrays()}
    with open(Path(path), "wb") as handle:  # a file handle: numpy must not append ".npz" to the name
        np.savez_compressed(
            handle, version=np.int32(FLOW_FORMAT_VERSION),
            sample_token=np.asarray([r.sample_token for r in recs], dtype=str),
            box_start=np.cumsum([0] + [len(r.box_index) for r in recs]).astype(np.int64),
            move_start=np.cumsum([0] + [len(r.offset) for r in recs]).astype(np.int64), **tables)


def load_flow_records(path) -> dict[str, FlowRecord]:
    """Read a file written by ``save_flow_records`` → {sample_token: FlowRecord}. Checks the format version."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable flow file ({exc})") from exc
    with data:
        needed = ["version", "sample_token", "box_start", "move_start", *FlowRecord("").arrays()]
        missing = [k for k in needed if k not in data.files]
        if missing:
            raise ValueError(f"{path}: flow file misses {missing}")
        version = int(data["version"])
        if version != FLOW_FORMAT_VERSION:
            raise ValueError(f"{path}: flow format version {version}, this code reads {FLOW_FORMAT_VERSION}; "
                             "rerun `occflownet prepare`")
        t = {k: data[k] for k in data.files}
    bs, ms = t["box_start"], t["move_start"]
    out = {}
    for n, token in enumerate(t["sample_token"].tolist()):
        b, m = slice(bs[n], bs[n + 1]), slice(ms[n], ms[n + 1])
        out[token] = FlowRecord(token, t["box_index"][b], t["label"][b], t["center"][b], t["size_wlh"][b],
                                t["rotation"][b], t["offset"][m], t["move_box"][m], t["transform"][m], version)
    return out


def flow_path(dataroot, version: str) -> Path:
    """Where ``prepare`` writes the flow records of a root: beside the sample index."""
    from .index import index_dir

    return index_dir(dataroot, version) / "flow.npz"


# Keyframes from which precompute_flow runs a process pool: below, starting the workers costs more than it saves.
PARALLEL_FROM = 2000


def precompute_flow(index, dataroot, horizon: int = 3, progress: bool = False, workers: int | None = None) -> Path:
    """Flow records of every keyframe of ``index`` (``keyframe_flow``), written once to ``flow_path``.

    Parallel over keyframes (a process pool once there are :data:`PARALLEL_FROM` of them); deterministic, so
    re-running writes the same file, serial or parallel. The workers are started, not forked (a fork inherits the
    OpenMP runtime of a process that may have run parallel kernels, the hang the training loader met), and receive
    the index once each, not with every job. ``flow.json`` beside it records the horizon it was computed for."""
    import os
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    positions = list(range(len(index)))
    workers = workers if workers is not None else min(4, os.cpu_count() or 1)
    bar = dict(total=len(positions), desc="flow", unit="keyframe", disable=not progress)
    if workers > 1 and len(positions) >= PARALLEL_FROM:
        chunk = max(1, len(positions) // (workers * 8))
        with ProcessPoolExecutor(workers, mp_context=spawn_context(),
                                 initializer=_set_worker_index, initargs=(index,)) as pool:
            records = list(tqdm(pool.map(_keyframe_flow_job, [(p, horizon) for p in positions], chunksize=chunk),
                                **bar))
    else:
        records = [keyframe_flow(index, p, horizon) for p in tqdm(positions, **bar)]
    path = flow_path(dataroot, index.version)
    with atomic_path(path) as tmp:
        save_flow_records(tmp, records)
    path.with_suffix(".json").write_text(json.dumps({"horizon": int(horizon), "format_version": FLOW_FORMAT_VERSION,
                                                     "keyframes": len(records)}))
    return path


def flow_horizon(dataroot, version: str) -> int | None:
    """The horizon the written flow records cover (None when ``prepare`` wrote none)."""
    meta = flow_path(dataroot, version).with_suffix(".json")
    return int(json.loads(meta.read_text())["horizon"]) if meta.is_file() else None


_WORKER_INDEX = None          # the SampleIndex of a precompute_flow worker process (set by its initializer)


def _set_worker_index(index) -> None:
    global _WORKER_INDEX
    _WORKER_INDEX = index


def _keyframe_flow_job(job) -> FlowRecord:
    position, horizon = job
    return keyframe_flow(_WORKER_INDEX, position, horizon)
