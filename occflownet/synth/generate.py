"""Write a synthetic dataset in the exact nuScenes (+ lidarseg, + Occ3D) layout, then label it.

    ROOT/<version>/{13 tables}.json, lidarseg.json, splits.json
    ROOT/samples/CAM_*/<log>__<channel>__<timestamp>.jpg
    ROOT/samples/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin   float32 [N, 5] (x, y, z, intensity, ring), LiDAR frame
    ROOT/sweeps/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin    the LiDAR sweeps between keyframes (no lidarseg)
    ROOT/lidarseg/<version>/<lidar sample_data token>_lidarseg.bin  uint8 [N] raw lidarseg index (keyframes)
    ROOT/gts/<scene name>/<sample token>/labels.npz                 Occ3D labels, made by occflownet.labels
    ROOT/truth/<scene name>/<sample token>/semantics.npz            the geometry voxelised (checks the labels only)
    ROOT/maps/<map token>.png, ROOT/preview/<sample token>.png (with preview=True)

Cameras are written at keyframes only; the LiDAR also at ``sweeps`` times between consecutive keyframes.
"""
from __future__ import annotations

import io
import json
import shutil
import sys
import time
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from occflownet.occ3d import CAMERAS, DRIVEABLE_SURFACE, LIDAR
from occflownet.geometry import yaw_to_quaternion
from occflownet.labels import LabelConfig, label_root
from occflownet.labels.npz import write_uint8_npz
from occflownet.options import check_fields, option
from occflownet.synth.frame import Keyframe, SensorRig, render_keyframe, render_sweep, sweep_times_us
from occflownet.synth.layout import WorldConfig, build_world
from occflownet.synth.writer import (Tables, calibrated_sensor_records, link, pose_record, token,
                                     visibility_token)

DEFAULT_VERSION = "v1.0-trainval"
DEFAULT_SWEEPS = 4  # LiDAR sweeps between keyframes (10 Hz; nuScenes records 9, at 20 Hz)
FIRST_TIMESTAMP_US = 1533151603000000
ANNOTATION_RANGE_M = 70.0  # agents whose centre is this close to the ego (xy) are annotated (covers the grid)


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`generate` writes besides the scenes' layout (:class:`~occflownet.synth.layout.WorldConfig`):
    how many scenes and keyframes, images and sweeps, and how it treats a folder that holds a dataset.
    `occflownet synth` derives its options from these fields (``occflownet/options.py``)."""

    scenes: int = option(1, "number of scenes, the val split's included", minimum=1)
    frames: int = option(6, "keyframes per scene, 2 Hz", minimum=1)
    val_scenes: int = option(1, "scenes of the val split: the last ones (with no more scenes than this, every "
                                "scene is in both splits)", minimum=1)
    val_frames: int = option(0, "keyframes of each val scene; 0: --frames", minimum=0)
    seed: int = option(0, "random seed; same seed, same files")
    width: int = option(480, "image width in pixels (0.3 x nuScenes)", minimum=16)
    height: int = option(270, "image height in pixels", minimum=16)
    sweeps: int = option(DEFAULT_SWEEPS, "LiDAR sweeps between consecutive keyframes (nuScenes has 9)", minimum=0)
    version: str = option(DEFAULT_VERSION, "dataset version folder")
    preview: bool = option(False, "also write DIR/preview/<sample token>.png")
    overwrite: bool = option(False, "replace a dataset already in DIR")

    def __post_init__(self):
        check_fields(self)


@dataclass
class SynthResult:
    root: Path
    version: str
    scene_names: list[str]
    num_samples: int
    seconds: float


def truth_path(root, scene_name: str, sample_token: str) -> Path:
    """Where ``generate`` writes a keyframe's geometric truth: ``semantics`` uint8 [200, 200, 16] (17 free), every
    surface of the world voxelised (``synth.voxelize``). It checks the labels in ``gts/``; it is never the
    benchmark."""
    return Path(root) / "truth" / scene_name / sample_token / "semantics.npz"


def load_truth(root, scene_name: str, sample_token: str) -> np.ndarray:
    """The geometric truth of a keyframe (``truth_path``)."""
    with np.load(truth_path(root, scene_name, sample_token)) as z:
        return z["semantics"]


def _clear(root: Path, version: str, overwrite: bool) -> None:
    if (root / version).exists() and any((root / version).iterdir()):
        if not overwrite:
            raise FileExistsError(f"{root / version} already holds a dataset; pass overwrite=True (--overwrite)")
        for sub in (root / version, root / "samples", root / "sweeps", root / "lidarseg" / version, root / "gts",
                    root / "truth", root / "maps", root / "preview"):
            if sub.exists():
                shutil.rmtree(sub)


def generate(out, settings: SynthConfig = SynthConfig(), *, config: WorldConfig = WorldConfig(),
             rig: SensorRig | None = None, progress: bool = True, labels: LabelConfig = LabelConfig(),
             **changes) -> SynthResult:
    """Generate ``settings.scenes`` scenes of ``settings.frames`` keyframes each (the val scenes, the last
    ``settings.val_scenes``, ``settings.val_frames`` when set) under ``out`` (``settings.sweeps`` LiDAR sweeps
    between consecutive keyframes), laid out by ``config``, then label it with ``labels``
    (``occflownet.labels.label_root``). ``changes``: fields of :class:`SynthConfig` that replace those of
    ``settings`` (``generate(out, scenes=2, seed=3)``). Deterministic for the seed."""
    import cv2
    from tqdm import tqdm

    job = replace(settings, **changes)          # checks the values (SynthConfig.__post_init__)
    scenes, seed, version, sweeps = job.scenes, job.seed, job.version, job.sweeps
    val = job.val_scenes if scenes > job.val_scenes else 0    # the last scenes are val; none: all in both splits
    counts = [job.frames] * (scenes - val) + [job.val_frames or job.frames] * val   # keyframes per scene
    start = time.perf_counter()
    root = Path(out)
    _clear(root, version, job.overwrite)
    rig = rig or SensorRig.default(job.width, job.height)
    tables = Tables(seed)
    bar = tqdm(total=sum(counts), desc="synth keyframes", unit="kf", file=sys.stderr, disable=not progress)
    scene_names, log_tokens, first_world = [], [], None
    for s, frames in enumerate(counts):
        world = build_world(config, seed, s, frames)
        first_world = first_world or world
        log_tokens.append(_write_scene(root, version, tables, rig, world, seed, s, frames, sweeps, bar, cv2))
        scene_names.append(world.name)
    bar.close()
    _write_map(root, tables, seed, first_world, log_tokens, cv2)
    tables.write(root / version)
    splits = {"train": scene_names[:-val], "val": scene_names[-val:]} if val else \
        {"train": scene_names, "val": scene_names}
    with open(root / version / "splits.json", "w") as f:
        json.dump(splits, f, indent=1)
    label_root(root, labels, version=version, progress=progress)
    if job.preview:
        _write_previews(root, version, cv2)
    return SynthResult(root, version, scene_names, sum(counts), time.perf_counter() - start)


def _write_scene(root, version, tables, rig, world, seed, s, frames, sweeps, bar, cv2) -> str:
    """Render scene ``s`` keyframe by keyframe (and the sweeps after each), write its files and add its table
    records; returns its log token."""
    key = f"scene{s}"
    logfile = f"n{seed % 1000:03d}-2018-08-{1 + s % 28:02d}-synth-{s:04d}"
    log_tok = token(seed, key, "log")
    tables.t["log"].append({"token": log_tok, "logfile": logfile, "vehicle": "synth-ego",
                            "date_captured": f"2018-08-{1 + s % 28:02d}", "location": "synth-city"})
    cs = calibrated_sensor_records(tables, key, rig.intrinsics, rig.cam2ego, rig.lidar2ego)
    t0 = FIRST_TIMESTAMP_US + s * 1_000_000_000
    samples, channel_sd = [], {ch: [] for ch in (*CAMERAS, LIDAR)}
    ann_by_agent: dict[int, list[dict]] = {}
    for k in range(frames):
        kf = render_keyframe(world, k, rig, t0, seed, s)
        sample_tok = token(seed, key, "sample", k)
        samples.append({"token": sample_tok, "timestamp": kf.lidar_time_us, "scene_token": token(seed, key)})
        records = _sensor_records(root, version, tables, rig, kf, key, k, logfile, sample_tok, cs, cv2)
        for ch, rec in records.items():
            channel_sd[ch].append(rec)
        for idx, ann in _annotations(world, kf, key, k, sample_tok, tables).items():
            ann_by_agent.setdefault(idx, []).append(ann)
        write_uint8_npz(truth_path(root, world.name, sample_tok), semantics=kf.truth)
        if k + 1 < frames:
            channel_sd[LIDAR] += _sweep_records(root, tables, rig, world, seed, s, t0, key, k, sweeps, logfile, cs,
                                                (sample_tok, token(seed, key, "sample", k + 1)))
        bar.update(1)
    _link_scene(tables, world, seed, key, log_tok, samples, channel_sd, ann_by_agent)
    return log_tok


def _sweep_records(root, tables, rig, world, seed, s, t0, key, k, sweeps, logfile, cs, nearest) -> list[dict]:
    """Write the LiDAR sweeps between keyframes k and k + 1 (no lidarseg, like nuScenes); return their sample_data
    records (time order). ``nearest``: the two keyframes' sample tokens; a sweep belongs to the nearer one."""
    out = []
    (root / "sweeps" / LIDAR).mkdir(parents=True, exist_ok=True)
    for j, us in enumerate(sweep_times_us(t0, k, sweeps)):
        scan, pose = render_sweep(world, us, rig, t0, seed, s)
        sd_tok = token(tables.seed, key, "sample_data", LIDAR, k, "sweep", j)
        ego_tok = token(tables.seed, key, "ego_pose", LIDAR, k, "sweep", j)
        tables.t["ego_pose"].append(pose_record(ego_tok, pose, timestamp=us))
        rel = f"sweeps/{LIDAR}/{logfile}__{LIDAR}__{us}.pcd.bin"
        scan.points.astype(np.float32).tofile(root / rel)
        out.append({"token": sd_tok, "sample_token": nearest[0] if 2 * (j + 1) <= sweeps + 1 else nearest[1],
                    "ego_pose_token": ego_tok, "calibrated_sensor_token": cs[LIDAR], "timestamp": us,
                    "fileformat": "pcd", "is_key_frame": False, "height": 0, "width": 0, "filename": rel})
    return out


def _write_previews(root, version, cv2) -> None:
    """preview/<sample token>.png for every keyframe, from the files written (labels included)."""
    from occflownet.data.builder import build_index
    from occflownet.synth.preview import preview_sample

    index = build_index(root, version)
    (root / "preview").mkdir(parents=True, exist_ok=True)
    for p in range(len(index)):
        picture = preview_sample(root, index[p])
        cv2.imwrite(str(root / "preview" / f"{index.tokens[p]}.png"), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))


def _link_scene(tables, world, seed, key, log_tok, samples, channel_sd, ann_by_agent) -> None:
    """Chain one scene's samples, sample_data and annotations (prev/next) and add them, its instances and the
    scene record to the tables."""
    link(samples)
    tables.t["sample"] += samples
    for recs in channel_sd.values():
        link(recs)
        tables.t["sample_data"] += recs
    for idx in sorted(ann_by_agent):
        anns = ann_by_agent[idx]
        link(anns)
        tables.t["sample_annotation"] += anns
        tables.t["instance"].append({
            "token": anns[0]["instance_token"], "category_token": tables.category_token(world.agents[idx].raw),
            "nbr_annotations": len(anns), "first_annotation_token": anns[0]["token"],
            "last_annotation_token": anns[-1]["token"]})
    tables.t["scene"].append({
        "token": token(seed, key), "log_token": log_tok, "nbr_samples": len(samples),
        "first_sample_token": samples[0]["token"], "last_sample_token": samples[-1]["token"],
        "name": world.name, "description": _describe(world, seed)})


def _write_map(root, tables, seed, first_world, log_tokens, cv2) -> None:
    """The map table and its drivable-area mask PNG (1 px = 1 m) of the first scene."""
    map_tok = token(seed, "map")
    (root / "maps").mkdir(parents=True, exist_ok=True)
    drivable = (first_world.ground.cls[::10, ::10] == DRIVEABLE_SURFACE).astype(np.uint8) * 255
    cv2.imwrite(str(root / "maps" / f"{map_tok}.png"), drivable)
    tables.t["map"] = [{"token": map_tok, "log_tokens": log_tokens, "category": "semantic_prior",
                        "filename": f"maps/{map_tok}.png"}]


def _sensor_records(root, version, tables, rig, kf: Keyframe, key, k, logfile, sample_tok, cs, cv2) -> dict:
    """Write one keyframe's images, point cloud and lidarseg labels; return channel → sample_data record."""
    out = {}
    entries = [(ch, kf.camera_times_us[c], kf.camera_ego2global[c]) for c, ch in enumerate(CAMERAS)]
    entries.append((LIDAR, kf.lidar_time_us, kf.lidar_ego2global))
    for c, (ch, us, pose) in enumerate(entries):
        sd_tok = token(tables.seed, key, "sample_data", ch, k)
        ego_tok = token(tables.seed, key, "ego_pose", ch, k)
        tables.t["ego_pose"].append(pose_record(ego_tok, pose, timestamp=us))
        ext = "jpg" if ch != LIDAR else "pcd.bin"
        rel = f"samples/{ch}/{logfile}__{ch}__{us}.{ext}"
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)
        if ch != LIDAR:
            bgr = cv2.cvtColor(kf.cameras[c].rgb, cv2.COLOR_RGB2BGR)
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 92])
            (root / rel).write_bytes(buf.tobytes())
            w, h = rig.width, rig.height
        else:
            kf.scan.points.astype(np.float32).tofile(root / rel)
            seg = f"lidarseg/{version}/{sd_tok}_lidarseg.bin"
            (root / "lidarseg" / version).mkdir(parents=True, exist_ok=True)
            kf.scan.raw.astype(np.uint8).tofile(root / seg)
            tables.lidarseg.append({"token": sd_tok, "sample_data_token": sd_tok, "filename": seg})
            w = h = 0
        out[ch] = {"token": sd_tok, "sample_token": sample_tok, "ego_pose_token": ego_tok,
                   "calibrated_sensor_token": cs[ch], "timestamp": us, "fileformat": ext.split(".")[0],
                   "is_key_frame": True, "height": h, "width": w, "filename": rel}
    return out


def _annotations(world, kf: Keyframe, key, k, sample_tok, tables) -> dict[int, dict]:
    """sample_annotation records (prev/next unset) of the agents near the ego at this keyframe, by agent index."""
    t = kf.scene_time
    ego_xy = kf.lidar_ego2global[:2, 3]
    inst = kf.boxes.instance
    n_agents = len(world.agents)
    visible = np.zeros(n_agents + 1, np.int64)
    alone = np.zeros(n_agents + 1, np.int64)
    for cam in kf.cameras:
        visible += np.bincount(np.where(inst >= 0, inst, n_agents), weights=cam.visible,
                               minlength=n_agents + 1).astype(np.int64)
        alone += np.bincount(np.where(inst >= 0, inst, n_agents), weights=cam.alone,
                             minlength=n_agents + 1).astype(np.int64)
    pts = np.bincount(kf.scan.instance[kf.scan.instance >= 0], minlength=n_agents)
    out = {}
    for i, agent in enumerate(world.agents):
        center, yaw = world.annotation_box(i, t)
        if np.hypot(*(center[:2] - ego_xy)) > ANNOTATION_RANGE_M:
            continue
        frac = visible[i] / alone[i] if alone[i] else 0.0
        out[i] = {
            "token": token(tables.seed, key, "sample_annotation", i, k), "sample_token": sample_tok,
            "instance_token": token(tables.seed, key, "instance", i), "visibility_token": visibility_token(frac),
            "attribute_tokens": [tables.attribute_token(agent.attribute)] if agent.attribute else [],
            "translation": [float(v) for v in center], "size": [float(v) for v in agent.size],
            "rotation": [float(v) for v in yaw_to_quaternion(yaw)], "prev": "", "next": "",
            "num_lidar_pts": int(pts[i]), "num_radar_pts": 0}
    return out


def _describe(world, seed) -> str:
    m = world.meta
    return (f"synthetic street, seed {seed}: {m['lanes']} lane(s) per direction"
            f"{', cross street' if m['cross_street'] else ''}, ego {world.ego_speed:.1f} m/s")
