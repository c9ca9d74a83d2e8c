"""The label pipeline end to end on the hand-built nuScenes root (tests/nuscenes_fixture.py: walls, ground, a car
driving 22 m through the scene, a walking pedestrian, LiDAR sweeps between keyframes) and on the real nuScenes frame:
moving boxes, the definition's invariants, sweep labels, reruns, bad input, shards and workers."""
import shutil
from pathlib import Path

import numpy as np
import pytest

from occflownet.occ3d import CAR, FREE, GRID, map_lidarseg
from occflownet.data.builder import build_index
from occflownet.data.tables import DatasetError
from occflownet.geometry import invert, transform_points
from occflownet.labels import LabelConfig, LabelError, label_root
from nuscenes_fixture import MOVERS, SCENES, mover_box, mover_points, write_fixture

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """(fixture, labels folder) of the fixture root labelled with the default settings."""
    base = tmp_path_factory.mktemp("labels")
    fx = write_fixture(base / "root", write_images=False)
    report = label_root(fx.root, out=base / "out", progress=False)
    assert report.written == sum(n for _, n, _ in SCENES) and not report.warnings
    return fx, base / "out" / "gts"


def _labels(gts: Path, scene: str, token: str) -> dict:
    with np.load(gts / scene / token / "labels.npz") as z:
        return {k: z[k] for k in z.files}


def _box_distance(points: np.ndarray, box2ego: np.ndarray, size) -> np.ndarray:
    """Distance [N] of ego points to a box (0 inside); size (w, l, h)."""
    local = np.abs(transform_points(invert(box2ego), points))
    return np.linalg.norm(np.maximum(local - np.array([size[1], size[0], size[2]]) / 2, 0), axis=1)


def test_a_moving_car_leaves_no_trail_and_is_densified(labelled):
    """The car moves 22 m through scene-a; its returns of every keyframe and sweep, moved by its box, land in its
    box of the keyframe labelled: every one of its 13 sweeps' points lies on the box, and no car voxel lies more
    than one voxel outside it."""
    from occflownet.data.sweeps import scene_sweeps
    from occflownet.data.tables import load_tables
    from occflownet.labels.accumulate import keyframe_cloud, load_scene_cloud

    fx, gts = labelled
    index = build_index(fx.root)
    sweeps = scene_sweeps(load_tables(fx.root), index)["scene-a"]
    cloud = load_scene_cloud(fx.root, index, sweeps, 0, 5, LabelConfig())
    car = next(m for m in MOVERS if m[0] == "car")
    for p, token in enumerate(fx.sample_tokens["scene-a"]):
        box = invert(index[p].ego2global) @ mover_box(car, p * 0.5)
        points = keyframe_cloud(cloud, index[p].ego2global, index[p].lidar.timestamp, np.ones(len(sweeps), bool))
        on_car = points.label == CAR
        assert on_car.sum() == len(sweeps) * len(mover_points(car))            # all 13 sweeps, none lost
        assert _box_distance(points.points[on_car], box, car[3]).max() < 1e-4  # on the box (float32 files)
        sem = _labels(gts, "scene-a", token)["semantics"]
        ijk = np.argwhere(sem == CAR)
        centres = np.asarray(GRID.lower) + (ijk + 0.5) * GRID.voxel_size
        reach = GRID.voxel_size + GRID.voxel_size * np.sqrt(3) / 2   # one voxel out, measured from voxel centres
        assert len(ijk) > 20 and _box_distance(centres, box, car[3]).max() <= reach


def test_labels_follow_the_definition(labelled):
    """mask_camera inside mask_lidar; an occupied voxel holds a true surface point of the keyframe (static points
    where they are, the movers' points placed by their boxes at the keyframe) with the class of the points there;
    camera and LiDAR masks hold most of the scene's surfaces."""
    fx, gts = labelled
    index = build_index(fx.root)
    for p in range(len(index)):
        sample = index[p]
        lab = _labels(gts, sample.scene_name, sample.token)
        sem, ml, mc = lab["semantics"], lab["mask_lidar"].astype(bool), lab["mask_camera"].astype(bool)
        assert not (mc & ~ml).any() and mc.sum() > 1000 and (sem != FREE).sum() > 500
        to_ego = invert(sample.ego2global)
        pts = [transform_points(to_ego, fx.static)]
        cls = [map_lidarseg(fx.static_raw)]
        for m in MOVERS:
            pts.append(transform_points(to_ego @ mover_box(m, sample.index_in_scene * 0.5), mover_points(m)))
            cls.append(map_lidarseg(np.full(len(pts[-1]), m[2], np.uint8)))
        pts, cls = np.concatenate(pts), np.concatenate(cls)
        inside = GRID.contains(pts)
        truth = np.full(GRID.shape, FREE, np.uint8)
        ijk = GRID.index_of(pts[inside])
        truth[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = cls[inside]
        occupied = sem != FREE
        assert (truth[occupied] != FREE).all(), f"{sample.token}: occupied voxels without a surface point"
        assert (sem[occupied] == truth[occupied]).mean() > 0.97
        assert ml[occupied].mean() > 0.95 and mc[occupied].mean() > 0.3


def test_sweep_points_take_the_class_of_their_neighbours(labelled):
    from occflownet.data.sweeps import scene_sweeps
    from occflownet.data.tables import load_tables
    from occflownet.labels.accumulate import load_scene_cloud
    from occflownet.labels.config import UNLABELLED

    fx, _ = labelled
    tables = load_tables(fx.root)
    index = build_index(fx.root)
    sweeps = scene_sweeps(tables, index)["scene-a"]
    assert len(sweeps) == 5 + 4 * 2 and sum(s.keyframe is not None for s in sweeps) == 5
    assert [s.timestamp for s in sweeps] == sorted(s.timestamp for s in sweeps)
    cloud = load_scene_cloud(fx.root, index, sweeps, 0, 5, LabelConfig())
    static = np.ones(len(cloud), bool)
    static[cloud.moving] = False
    from scipy.spatial import cKDTree

    dist, which = cKDTree(fx.static).query(cloud.xyz[static])
    on_static = dist < 1e-3                          # the fixture's static points, seen again by every sweep
    assert on_static.sum() > 12 * 2500
    assert np.array_equal(cloud.label[static][on_static], map_lidarseg(fx.static_raw)[which[on_static]])  # class ids
    assert cloud.unlabelled_sweep_points == 0         # every sweep point was seen by a keyframe too
    assert (cloud.label[cloud.moving] != UNLABELLED).all() and len(cloud.moving) == len(sweeps) * 2 * 120


def test_rerun_skips_refuses_other_settings_and_foreign_labels(tmp_path):
    fx = write_fixture(tmp_path / "root", write_images=False)
    first = label_root(fx.root, progress=False)
    assert first.written == 7 and first.skipped == 0
    again = label_root(fx.root, progress=False)
    assert again.written == 0 and again.skipped == 7
    victim = fx.root / "gts" / "scene-a" / fx.sample_tokens["scene-a"][2] / "labels.npz"
    before = victim.read_bytes()
    victim.unlink()                                                  # as if a run had been killed there
    resumed = label_root(fx.root, progress=False)
    assert resumed.written == 1 and victim.read_bytes() == before    # the same bytes as the first time
    with pytest.raises(LabelError, match="other settings"):
        label_root(fx.root, config=LabelConfig(window=1), progress=False)
    assert label_root(fx.root, config=LabelConfig(window=1), overwrite=True, progress=False).written == 7
    foreign = tmp_path / "foreign"
    (foreign / "gts" / "scene-a").mkdir(parents=True)
    with pytest.raises(LabelError, match="did not write"):
        label_root(fx.root, out=foreign, progress=False)
    assert not list(fx.root.glob("gts/**/*.tmp*"))


def test_shards_and_workers_give_the_same_files(labelled, tmp_path):
    fx, gts = labelled
    parts = [label_root(fx.root, out=tmp_path / "sharded", shard=f"{i}/2", progress=False) for i in range(2)]
    assert sorted(parts[0].scenes + parts[1].scenes) == ["scene-a", "scene-b"]
    assert not set(parts[0].scenes) & set(parts[1].scenes)
    label_root(fx.root, out=tmp_path / "workers", workers=2, progress=False)
    for f in sorted(gts.glob("*/*/labels.npz")):
        rel = f.relative_to(gts)
        assert (tmp_path / "sharded" / "gts" / rel).read_bytes() == f.read_bytes()
        assert (tmp_path / "workers" / "gts" / rel).read_bytes() == f.read_bytes()
    with pytest.raises(ValueError, match="shard"):
        label_root(fx.root, out=tmp_path / "x", shard="2/2", progress=False)


def test_bad_input_is_named(tmp_path):
    fx = write_fixture(tmp_path / "root", write_images=False)
    (fx.root / fx.version / "lidarseg.json").unlink()
    with pytest.raises(LabelError, match="--geometry-only"):
        label_root(fx.root, progress=False)
    geometry = label_root(fx.root, config=LabelConfig(geometry_only=True), progress=False)
    lab = _labels(fx.root / "gts", "scene-a", fx.sample_tokens["scene-a"][0])
    assert geometry.written == 7 and set(np.unique(lab["semantics"])) == {0, FREE} and lab["geometry_only"] == 1
    shutil.rmtree(fx.root / "gts")
    for ann in ("sample_annotation", "instance"):
        (fx.root / fx.version / f"{ann}.json").write_text("[]")
    warned = label_root(fx.root, config=LabelConfig(geometry_only=True), progress=False)
    assert len(warned.warnings) == 2 and "treated as static" in warned.warnings[0]
    broken = next((fx.root / "sweeps" / "LIDAR_TOP").iterdir())
    broken.write_bytes(b"\0" * 7)
    shutil.rmtree(fx.root / "gts")
    with pytest.raises(DatasetError, match=broken.name):
        label_root(fx.root, config=LabelConfig(geometry_only=True), progress=False)


@pytest.mark.skipif(not (SHARED / "nuscenes-frame" / "calib.json").is_file(), reason="../shared/data is not here")
def test_geometry_only_on_the_real_nuscenes_frame(tmp_path):
    """One real sweep, no lidarseg, no boxes: occupancy and masks by the definition."""
    from occflownet.data.frame_root import write_frame_root
    from occflownet.labels.config import LabelConfig as Config

    root = write_frame_root(SHARED / "nuscenes-frame", tmp_path / "frame")
    with pytest.raises(LabelError, match="lidarseg"):
        label_root(root, progress=False)
    report = label_root(root, config=Config(geometry_only=True), progress=False)
    assert report.written == 1 and "no annotated boxes" in report.warnings[0]
    lab = _labels(root / "gts", "frame-0001", report.keyframes[0]["token"])
    sem, ml, mc = lab["semantics"], lab["mask_lidar"].astype(bool), lab["mask_camera"].astype(bool)
    points = np.fromfile(SHARED / "nuscenes-frame" / "lidar.bin", np.float32).reshape(-1, 5)[:, :3]
    sample = build_index(root)[0]
    ego = transform_points(sample.lidar.sensor2ego, points.astype(np.float64))
    ijk = GRID.index_of(ego[GRID.contains(ego)])
    holds = np.zeros(GRID.shape, bool)
    holds[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    occupied = sem != FREE
    assert not (mc & ~ml).any() and (occupied <= holds).all() and occupied.sum() > 3000
    assert (mc & ~occupied).sum() > 10 * (mc & occupied).sum() > 0
