"""The label window (``LabelConfig.window``, ``occflownet labels --window K``): which sweeps a keyframe's labels
accumulate, by hand on made-up times and on the hand-built nuScenes root (tests/nuscenes_fixture.py), whose scene-a
has 5 keyframes 0.5 s apart with 2 sweeps between consecutive ones: 13 sweeps, keyframe k being sweep 3k."""
from types import SimpleNamespace

import numpy as np
import pytest

from nuscenes_fixture import LIDAR_SWEEPS, SCENES, write_fixture
from occflownet.labels import LabelConfig, label_root
from occflownet.labels.keyframe import window_sweeps

KEYFRAMES = 5
SWEEPS = (KEYFRAMES - 1) * (LIDAR_SWEEPS + 1) + 1


def test_window_sweeps_by_hand():
    """Keyframes at 0, 500, 1000, 1500, 2000 µs and a sweep every 100 µs (21 sweeps): window K keeps the sweeps from
    keyframe k − K to k + K, both ends included, clamped to the scene; None keeps all."""
    cloud = SimpleNamespace(sweep_time=np.arange(0, 2001, 100, dtype=np.int64))
    times = np.array([0, 500, 1000, 1500, 2000], np.int64)
    kept = lambda k, window: np.flatnonzero(window_sweeps(cloud, times, k, window)).tolist()
    assert kept(2, None) == list(range(21))
    assert kept(2, 0) == [10]                                        # the keyframe's own sweep
    assert kept(2, 1) == list(range(5, 16))                          # 500 .. 1500 µs
    assert kept(0, 1) == list(range(0, 6)) and kept(4, 1) == list(range(15, 21))   # clamped at the ends
    assert kept(1, 3) == list(range(21)) and kept(2, 2) == list(range(21))
    with pytest.raises(ValueError, match="window"):
        LabelConfig(window=-1)


@pytest.fixture(scope="module")
def windows(tmp_path_factory):
    """{window: {keyframe position in scene-a: its report entry}} for windows None, 0, 1, 2 (scene-a only), the
    points of each of scene-a's 13 sweeps, and the labels folders."""
    from occflownet.data.builder import build_index
    from occflownet.data.sweeps import scene_sweeps
    from occflownet.data.tables import load_tables
    from occflownet.labels.accumulate import load_scene_cloud

    assert SCENES[0][:2] == ("scene-a", KEYFRAMES)
    base = tmp_path_factory.mktemp("window")
    fx = write_fixture(base / "root", write_images=False)
    tokens = fx.sample_tokens["scene-a"]
    reports, folders = {}, {}
    for window in (None, 0, 1, 2):
        folders[window] = base / f"window-{window}"
        report = label_root(fx.root, config=LabelConfig(window=window), out=folders[window], shard="0/2",
                            progress=False)
        assert report.written == KEYFRAMES
        reports[window] = {tokens.index(k["token"]): k for k in report.keyframes}
    index = build_index(fx.root)
    sweeps = scene_sweeps(load_tables(fx.root), index)["scene-a"]
    cloud = load_scene_cloud(fx.root, index, sweeps, 0, KEYFRAMES, LabelConfig())
    assert len(cloud.sweep_time) == SWEEPS == 13
    per_sweep = np.bincount(cloud.sweep, minlength=SWEEPS)
    assert per_sweep.min() > 1000                                    # every sweep brings points
    return reports, per_sweep, folders, tokens


def test_the_window_decides_which_sweeps_a_keyframe_accumulates(windows):
    """Each keyframe's labels count the points of exactly the sweeps of its window: sweeps 3·max(k − K, 0) to
    3·min(k + K, 4) (the sweeps between keyframes included), all 13 without a window."""
    reports, per_sweep, _, _ = windows
    for window, report in reports.items():
        for k, entry in report.items():
            if window is None:
                first, last = 0, SWEEPS - 1
            else:
                first = (LIDAR_SWEEPS + 1) * max(k - window, 0)
                last = (LIDAR_SWEEPS + 1) * min(k + window, KEYFRAMES - 1)
            assert entry["points"] == int(per_sweep[first:last + 1].sum()), (window, k)


def test_a_wider_window_observes_more_and_one_covering_the_scene_is_the_whole_scene(windows):
    reports, _, folders, tokens = windows
    for k in range(KEYFRAMES):
        seen = [reports[w][k]["mask_lidar"] for w in (0, 1, 2, None)]
        assert seen == sorted(seen) and seen[0] < seen[-1], (k, seen)
    # from the middle keyframe a window of 2 reaches both ends: the same labels, byte for byte, as no window
    middle = f"scene-a/{tokens[2]}/labels.npz"
    assert (folders[2] / "gts" / middle).read_bytes() == (folders[None] / "gts" / middle).read_bytes()
    assert (folders[1] / "gts" / middle).read_bytes() != (folders[None] / "gts" / middle).read_bytes()
