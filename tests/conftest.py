"""Shared fixtures. ``synth_root``: one small synthetic nuScenes-format world, generated once per test session."""
from __future__ import annotations

import pytest

# The world behind ``synth_root``: 1 scene × 6 keyframes, 160×90 images, a 60 m margin (fewer agents, faster).
SYNTH_PARAMS = {"scenes": 1, "frames": 6, "seed": 7, "width": 160, "height": 90, "margin": 60.0}


@pytest.fixture(scope="session")
def synth_params() -> dict:
    """The parameters ``synth_root`` was generated with (a copy; rebuild the world with ``synth_world``)."""
    return dict(SYNTH_PARAMS)


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory):
    """(root Path, version str) of a small synthetic dataset in the nuScenes layout (see docs/data.md):
    1 scene (``scene-0001``, in both the train and val splits) × 6 keyframes, 160×90 images, LiDAR, lidarseg,
    boxes and Occ3D labels (gts/<scene>/<sample token>/labels.npz)."""
    from occflownet.synth.generate import DEFAULT_VERSION, generate
    from occflownet.synth.layout import WorldConfig

    p = SYNTH_PARAMS
    root = tmp_path_factory.mktemp("synth")
    generate(root, scenes=p["scenes"], frames=p["frames"], seed=p["seed"], width=p["width"], height=p["height"],
             config=WorldConfig(margin=p["margin"]), progress=False)
    return root, DEFAULT_VERSION


@pytest.fixture(scope="session")
def synth_world(synth_params):
    """(World, SensorRig, t0_us) behind ``synth_root``'s scene 0, in memory: ``render_keyframe(world, k, rig, t0_us,
    seed)`` reproduces keyframe k exactly (with depth, class and box buffers that are not written to disk)."""
    from occflownet.synth.frame import SensorRig
    from occflownet.synth.generate import FIRST_TIMESTAMP_US
    from occflownet.synth.layout import WorldConfig, build_world

    p = synth_params
    world = build_world(WorldConfig(margin=p["margin"]), p["seed"], 0, p["frames"])
    return world, SensorRig.default(p["width"], p["height"]), FIRST_TIMESTAMP_US


@pytest.fixture(scope="session")
def prepared_synth_root(synth_root, tmp_path_factory):
    """(root Path, version) of a copy of ``synth_root`` on which ``occflownet prepare`` has run (index, class
    counts, flow records), for tests of training and evaluation."""
    import shutil

    from occflownet.cli import main

    src, version = synth_root
    root = tmp_path_factory.mktemp("prepared") / "world"
    shutil.copytree(src, root)
    assert main(["prepare", "--dataroot", str(root), "--quiet"]) == 0
    return root, version
