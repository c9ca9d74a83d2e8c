"""The per-preset recipe lives in the library: TrainConfig(preset=p) is the run `occflownet train --preset p` is."""
import json

import pytest

from occflownet.cli import build_parser
from occflownet.commands.train import config_from_args
from occflownet.model.presets import PRESETS
from occflownet.train.recipe import PRESET_RECIPES, TrainConfig


def test_every_model_preset_has_a_recipe():
    assert set(PRESET_RECIPES) == set(PRESETS)


@pytest.mark.parametrize("preset", sorted(PRESET_RECIPES))
def test_config_from_python_equals_the_command_line_config(preset, prepared_synth_root, tmp_path):
    root, version = prepared_synth_root
    args = build_parser().parse_args(["train", "--preset", preset, "--dataroot", str(root), "--out", str(tmp_path)])
    from_cli = config_from_args(args)
    from_python = TrainConfig(preset=preset, dataroot=str(root), out=str(tmp_path), version=version)
    assert from_cli == from_python
    for name, value in PRESET_RECIPES[preset].items():
        assert getattr(from_python, name) == value, name


def test_recipe_values_are_resolved_and_overridable():
    cfg = TrainConfig(preset="tiny", lr=5e-4)
    assert (cfg.lr, cfg.rays_per_step, cfg.warmup_steps, cfg.ema_decay, cfg.checkpoint_every) == (5e-4, 4096, 50, 0.99,
                                                                                                   50)
    written = json.loads(json.dumps(cfg.to_dict()))                 # what train_config.json holds: no None left
    assert written["rays_per_step"] == 4096 and None not in [written[k] for k in PRESET_RECIPES["tiny"]]
    assert TrainConfig.from_dict(written) == cfg
    assert TrainConfig(preset="base").rays_per_step == 32768


def test_old_config_dicts_still_load():
    old = TrainConfig(preset="tiny").to_dict() | {"extra": {}}     # written before TrainConfig.extra was removed
    assert TrainConfig.from_dict(old) == TrainConfig(preset="tiny")


def test_unknown_preset_is_an_error():
    with pytest.raises(ValueError, match="unknown preset 'huge'"):
        TrainConfig(preset="huge")


@pytest.mark.parametrize("field", ["free_space", "free_beyond_grid"])
def test_free_rays_need_rendering_supervision(field):
    with pytest.raises(ValueError, match="need supervision '2d' or '2d\\+3d'"):
        TrainConfig(supervision="3d", **{field: True})
    cfg = TrainConfig(supervision="2d", **{field: True})
    assert cfg.uses_free_rays and not TrainConfig(supervision="2d").uses_free_rays


def test_free_stretches_before_the_points_need_rendering_supervision():
    with pytest.raises(ValueError, match="need supervision '2d' or '2d\\+3d'"):
        TrainConfig(supervision="3d", free_before_point=True)
    # they are stretches of the rendered rays, not free rays the data pipeline builds
    assert not TrainConfig(supervision="2d", free_before_point=True).uses_free_rays


def test_the_rendering_recipe_is_the_one_the_training_guide_recommends():
    import re
    import shlex
    from pathlib import Path

    from occflownet.train.recipe import RENDERING_RECIPE

    guide = (Path(__file__).parents[1] / "docs" / "training.md").read_text()
    spelled = re.search(r"The recommended 2D recipe[^`]*`(--supervision 2d[^`]*)`", guide)
    assert spelled, "docs/training.md no longer spells the recommended 2D recipe"
    args = build_parser().parse_args(["train", "--dataroot", "W", "--out", "R", "--version", "v",
                                      *shlex.split(spelled.group(1))])
    cfg = config_from_args(args)
    assert {name: getattr(cfg, name) for name in RENDERING_RECIPE} == RENDERING_RECIPE
    assert cfg.flow and cfg.horizon > 0        # the recipe's flow mover has flow to move
    default = TrainConfig()                                    # every entry changes something
    assert all(getattr(default, name) != value for name, value in RENDERING_RECIPE.items())
    assert TrainConfig(supervision="2d+3d", **RENDERING_RECIPE).uses_2d   # valid with either rendering mode
