"""The data reader and rays on the synthetic world (one geometry behind images, LiDAR, boxes and Occ3D labels)."""
import shutil
import time

import numpy as np
import pytest

from occflownet.cli import main
from occflownet.occ3d import STATIC_CLASSES
from occflownet.data.builder import build_index
from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.rays import RayBuilder, RayConfig, endpoint_classes


@pytest.fixture(scope="module")
def synth_index(synth_root):
    root, version = synth_root
    return build_index(root, version, verify_files=True)


def test_synth_root_is_indexed_completely(synth_root, synth_index, synth_params):
    root, _ = synth_root
    index = synth_index
    assert len(index) == synth_params["scenes"] * synth_params["frames"]
    assert {"all", "train", "val"} <= set(index.available_splits())
    for i in range(len(index)):
        s = index[i]
        assert s.lidarseg_path is not None and s.occupancy_path is not None
        assert s.image_sizes.tolist() == [[synth_params["width"], synth_params["height"]]] * 6
    s = index[1]
    assert len(s.boxes) > 0 and s.boxes_in_ego().centers.shape == (len(s.boxes), 3)
    images = load_sample_images(root, s)
    assert images.shape == (6, synth_params["height"], synth_params["width"], 3)


def _agreement(index, root, position, config):
    """Per t: fraction of ray endpoints whose Occ3D voxel holds the ray's label (all rays, static-class rays)."""
    rays = RayBuilder(index, root, config).rays(position)
    found = endpoint_classes(rays, load_occupancy(root, index[position].occupancy_path).semantics)
    assert (found != 255).mean() > 0.99
    same = found == rays.labels
    static = np.isin(rays.labels, STATIC_CLASSES)
    t = rays.time_offsets
    return {int(k): (same[t == k].mean(), same[(t == k) & static].mean()) for k in np.unique(t)}


def test_synth_rays_land_in_voxels_of_their_class(synth_root, synth_index):
    """Rays from every frame of the window, moved into the current ego frame, end in voxels of the current
    keyframe's Occ3D ground truth that carry their label: transforms, timestamps and labels all agree."""
    root, _ = synth_root
    position = min(3, len(synth_index) - 1)
    agreement = _agreement(synth_index, root, position, RayConfig())
    assert len(agreement) >= 4
    assert agreement[0][0] > 0.93, agreement
    for t, (_, static) in agreement.items():
        assert static > 0.85, (t, agreement)


def test_synth_rays_are_fast(synth_root, synth_index):
    root, _ = synth_root
    position = min(3, len(synth_index) - 1)
    builder = RayBuilder(synth_index, root, RayConfig(horizon=3), cache_size=0)
    start = time.perf_counter()
    rays = builder.rays(position)
    elapsed = time.perf_counter() - start
    assert len(np.unique(rays.time_offsets)) >= 6 and len(rays) > 10_000
    assert elapsed < 1.0, f"{elapsed:.2f} s for {len(np.unique(rays.time_offsets))} frames"


def test_synth_prepare_counts_agree_with_training_rays(synth_root, tmp_path):
    root, version = synth_root
    shutil.copytree(root / version, tmp_path / version)
    for sub in ("samples", "lidarseg"):  # LiDAR + labels are all counting needs; link, don't copy, the rest
        (tmp_path / sub).symlink_to(root / sub)
    assert main(["prepare", "--dataroot", str(tmp_path), "--version", version, "--quiet"]) == 0
    index = load_index(tmp_path, version)
    stats = index.class_stats
    assert stats.split == "train"
    builder = RayBuilder(index, tmp_path, RayConfig(horizon=0))
    ray_counts = np.zeros(17, dtype=np.int64)
    for position in index.split_positions("train"):
        ray_counts += np.bincount(builder.rays(int(position)).labels, minlength=17)
    # each counted point makes one t = 0 ray per camera it falls in: 1 to 3 of the six
    assert (stats.counts <= ray_counts).all() and (3 * stats.counts >= ray_counts).all()
    assert ray_counts.sum() < 1.5 * stats.counts.sum()
    present = stats.counts > 0
    assert present.sum() >= 8 and np.isclose(stats.weights[present].mean(), 1.0)
