import json
from dataclasses import asdict

import pytest

from occflownet.model import PRESETS, ModelConfig, get_preset
from occflownet.rig import default_rig


@pytest.mark.parametrize("name", ["tiny", "small", "base", "paper"])
def test_preset_round_trips_through_asdict_and_json(name):
    cfg = get_preset(name)
    assert cfg.preset == name
    assert ModelConfig(**asdict(cfg)) == cfg
    assert ModelConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_presets_match_the_design():
    base, paper = get_preset("base"), get_preset("paper")
    assert base.input_size == (256, 704) and base.backbone_layers == (3, 4, 6, 3)
    assert base.backbone_block == "bottleneck" and base.backbone_width == 64   # ResNet-50
    assert paper.input_size == (512, 1408) and paper.decoder_stride == 1
    assert paper.sigma_hidden == (256, 256, 256) and paper.semantic_hidden == (256, 256, 256)
    tiny = get_preset("tiny")
    assert 32 <= tiny.num_depth_bins <= 48 and tiny.decoder_stride > 1
    for cfg in (tiny, base, paper):
        assert cfg.threshold == 0.35
        assert cfg.default_calibration == default_rig(480, 270)


def test_small_is_tiny_with_a_denser_lifting_and_a_wider_backbone():
    """small differs from tiny only in its input size, depth bins and backbone width, and its frustum points fall
    into about five times as many distinct voxels of the default rig's view (the full-resolution skip is that much
    less sparse)."""
    import numpy as np
    import torch

    from occflownet.model.lift import frustum_points
    from occflownet.model.preprocess import preprocess_images, scale_intrinsics_to_features
    from occflownet.model.presets import FEATURE_STRIDE
    from occflownet.occ3d import GRID

    tiny, small = get_preset("tiny"), get_preset("small")
    assert asdict(small) | {"preset": "tiny", "input_size": tiny.input_size, "num_depth_bins": tiny.num_depth_bins,
                            "backbone_width": tiny.backbone_width} == asdict(tiny)
    cams = default_rig(480, 270)["cameras"].values()
    k = torch.tensor([c["intrinsic"] for c in cams], dtype=torch.float32)[None]
    cam2ego = torch.tensor([c["cam2ego"] for c in cams], dtype=torch.float32)[None]

    images = torch.zeros(1, 6, 270, 480, 3, dtype=torch.uint8)

    def voxels_hit(cfg):
        _, input_k = preprocess_images(images, k, cfg.input_size, cfg.image_mean, cfg.image_std)
        kf = scale_intrinsics_to_features(input_k, FEATURE_STRIDE)
        h, w = cfg.input_size[0] // FEATURE_STRIDE, cfg.input_size[1] // FEATURE_STRIDE
        points = frustum_points(kf, cam2ego, torch.tensor(cfg.depth_bin_centers()), h, w).reshape(-1, 3).numpy()
        ijk = GRID.index_of(points)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(GRID.shape)), axis=1)
        return len(np.unique(ijk[inside], axis=0))

    assert voxels_hit(small) > 4 * voxels_hit(tiny)


def test_depth_bins_span_1_to_45_m():
    cfg = get_preset("tiny", num_depth_bins=44)
    centers = cfg.depth_bin_centers()
    assert len(centers) == 44
    assert centers[0] == pytest.approx(1.5) and centers[-1] == pytest.approx(44.5)
    steps = {round(b - a, 9) for a, b in zip(centers, centers[1:])}
    assert steps == {1.0}
    edges = cfg.depth_bin_edges()
    assert edges[0] == 1.0 and edges[-1] == pytest.approx(45.0)


def test_get_preset_returns_independent_copies():
    cfg = get_preset("tiny")
    cfg.default_calibration["cameras"]["CAM_FRONT"]["intrinsic"][0][0] = -1
    cfg.threshold = 0.3
    assert PRESETS["tiny"].default_calibration["cameras"]["CAM_FRONT"]["intrinsic"][0][0] > 0
    assert get_preset("tiny").threshold == 0.35
    assert get_preset("tiny", threshold=0.3).threshold == 0.3


@pytest.mark.parametrize("bad", [
    {"input_size": (100, 288)}, {"backbone_block": "vit"}, {"backbone_layers": (1, 1, 1)},
    {"depth_min": 50.0}, {"decoder_stride": 3}, {"threshold": 1.5}, {"num_depth_bins": 1},
])
def test_invalid_configs_are_rejected(bad):
    with pytest.raises(ValueError):
        get_preset("tiny", **bad)


def test_unknown_preset_and_fields():
    with pytest.raises(ValueError, match="unknown model preset"):
        get_preset("huge")
    with pytest.raises(ValueError, match="unknown ModelConfig fields"):
        ModelConfig.from_dict({**get_preset("tiny").to_dict(), "colour": 1})
