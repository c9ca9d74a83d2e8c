"""`occflownet prepare` (index + class counts + flow hook) and the class-weight formula."""
import json
from types import SimpleNamespace

import numpy as np
import pytest
from nuscenes_fixture import SCENES, write_fixture, visible_hits

from occflownet.cli import main
from occflownet.occ3d import NUM_CLASSES, map_lidarseg
from occflownet.data.class_weights import (VOXEL_WEIGHT_CAP, ClassStats, class_weights, count_voxels,
                                           voxel_class_weights)
from occflownet.data.index import index_dir, load_index


def test_class_weights_formula():
    counts = np.zeros(NUM_CLASSES, dtype=np.int64)
    counts[[0, 4, 11]] = [100, 10, 890]
    w = class_weights(counts)
    raw = np.log(1000 / np.array([100, 10, 890]))
    np.testing.assert_allclose(w[[0, 4, 11]], raw / raw.mean(), rtol=1e-6)
    assert w[[0, 4, 11]].mean() == pytest.approx(1.0)
    assert w[4] > w[0] > w[11] > 0  # rarer classes weigh more
    assert (np.delete(w, [0, 4, 11]) == 0).all()  # absent classes: weight 0
    one = np.zeros(NUM_CLASSES, dtype=np.int64)
    one[3] = 7
    assert class_weights(one)[3] == 1.0 and class_weights(one).sum() == 1.0
    with pytest.raises(ValueError, match="no class"):
        class_weights(np.zeros(NUM_CLASSES))
    with pytest.raises(ValueError, match="17 non-negative"):
        class_weights(np.ones(5))


def test_voxel_class_weights_and_counts(tmp_path):
    """--voxel-weighting sqrt-balanced: w_c = √(N_free / N_c) between 1 and the cap; counted over the labels of the
    given keyframes, inside mask_camera when masked."""
    counts = np.zeros(NUM_CLASSES + 1, dtype=np.int64)
    counts[[4, 11, 8, 17]] = [100, 10_000, 1, 40_000]
    w = voxel_class_weights(counts)
    assert w[17] == 1.0 and w[4] == pytest.approx(20.0) and w[11] == pytest.approx(2.0)
    assert w[8] == VOXEL_WEIGHT_CAP and w[0] == 1.0                   # capped; absent classes make no term
    with pytest.raises(ValueError, match="no free voxel"):
        voxel_class_weights(np.r_[np.ones(NUM_CLASSES), 0])
    with pytest.raises(ValueError, match="18 non-negative"):
        voxel_class_weights(np.ones(NUM_CLASSES))
    semantics = np.full((200, 200, 16), 17, np.uint8)
    semantics[:2, :, 0] = 4                                         # 400 car voxels, 200 of them in the mask
    mask = np.zeros((200, 200, 16), np.uint8)
    mask[1:, :, :] = 1
    np.savez(tmp_path / "labels.npz", semantics=semantics, mask_lidar=mask, mask_camera=mask)
    index = {0: SimpleNamespace(occupancy_path="labels.npz"), 1: SimpleNamespace(occupancy_path="labels.npz")}
    every = count_voxels(tmp_path, index, [0, 1], masked=False)
    inside = count_voxels(tmp_path, index, [0, 1], masked=True)
    assert every[4] == 800 and every[17] == 2 * 200 * 200 * 16 - 800 and every.sum() == 2 * 200 * 200 * 16
    assert inside[4] == 400 and inside.sum() == 2 * mask.sum()


def _expected_counts(fx, scenes):
    counts = np.zeros(NUM_CLASSES, dtype=np.int64)
    for si, (name, n, _) in enumerate(SCENES):
        if name in scenes:
            for k in range(n):
                _, raw = fx.points_global(si, k)
                counts += np.bincount(map_lidarseg(raw)[visible_hits(fx, si, k) > 0], minlength=NUM_CLASSES)
    return counts


def test_prepare_writes_index_and_counts_and_is_idempotent(tmp_path, capsys):
    fx = write_fixture(tmp_path / "root", write_images=False)
    assert main(["prepare", "--dataroot", str(fx.root), "--quiet"]) == 0
    out = capsys.readouterr()
    assert "7 keyframes in 2 scenes" in out.out and "class counts over split 'all'" in out.out
    index = load_index(fx.root)
    stats = index.class_stats
    assert stats.split == "all" and stats.num_samples == 7
    np.testing.assert_array_equal(stats.counts, _expected_counts(fx, {"scene-a", "scene-b"}))
    np.testing.assert_allclose(stats.weights, class_weights(stats.counts))
    folder = index_dir(fx.root, fx.version)
    before = {name: (folder / name).read_bytes() for name in ("index.npz", "index.json")}

    assert main(["prepare", "--dataroot", str(fx.root), "--version", fx.version, "--quiet"]) == 0
    assert "class counts: up to date (split all), reused" in capsys.readouterr().err
    assert {name: (folder / name).read_bytes() for name in before} == before

    # a named training split: counted by default, recounted because the split changed
    (fx.root / fx.version / "splits.json").write_text(json.dumps({"train": ["scene-a"], "val": ["scene-b"]}))
    assert main(["prepare", "--dataroot", str(fx.root), "--quiet"]) == 0
    stats = load_index(fx.root).class_stats
    assert stats.split == "train" and stats.num_samples == 5
    np.testing.assert_array_equal(stats.counts, _expected_counts(fx, {"scene-a"}))
    assert main(["prepare", "--dataroot", str(fx.root), "--split", "val", "--quiet"]) == 0
    assert load_index(fx.root).class_stats.split == "val"


def test_prepare_errors(tmp_path, capsys):
    fx = write_fixture(tmp_path / "root", write_images=False)
    assert main(["prepare", "--dataroot", str(fx.root), "--split", "test", "--quiet"]) == 2
    assert "unknown split 'test'; available: all" in capsys.readouterr().err
    (fx.root / fx.version / "sample.json").unlink()
    assert main(["prepare", "--dataroot", str(fx.root), "--version", fx.version]) == 1
    assert "table 'sample' is missing" in capsys.readouterr().err
    assert main(["prepare", "--dataroot", str(tmp_path / "nowhere")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_prepare_writes_flow_records_for_every_keyframe_idempotently(tmp_path):
    from occflownet.data.flow import flow_horizon, flow_path, load_flow_records

    fx = write_fixture(tmp_path / "root", write_images=False)
    assert main(["prepare", "--dataroot", str(fx.root), "--skip-class-counts", "--quiet", "--flow-horizon", "2"]) == 0
    index = load_index(fx.root)
    path = flow_path(fx.root, index.version)
    records = load_flow_records(path)
    assert set(records) == set(index.tokens)
    assert flow_horizon(fx.root, index.version) == 2
    assert all(abs(t) <= 2 for r in records.values() for t in r.offsets)
    first = path.read_bytes()
    assert main(["prepare", "--dataroot", str(fx.root), "--skip-class-counts", "--quiet", "--flow-horizon", "2"]) == 0
    assert path.read_bytes() == first
    assert load_index(fx.root).class_stats is None


def test_class_stats_round_trip():
    stats = ClassStats("train", 3, np.arange(17), class_weights(np.arange(17)))
    back = ClassStats.from_dict(json.loads(json.dumps(stats.to_dict())))
    assert back.split == "train" and back.num_samples == 3
    np.testing.assert_array_equal(back.counts, stats.counts)
    np.testing.assert_allclose(back.weights, stats.weights)
