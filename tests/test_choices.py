"""Each set of choices has one definition (occflownet/choices.py) that the command line, the configurations and
their checks read; the command lines of `train` and `quickstart` are derived from their dataclasses, every field is
reachable, and the quickstart's printed train command parses back to the config it runs."""
from __future__ import annotations

import ast
import dataclasses
import shlex
from pathlib import Path

import pytest

from occflownet import choices
from occflownet.choices import (FLOW_MOVERS, FREE_STRETCH_RULES, HEAD_INITS, INT8_RANGES, LR_SCHEDULES, PRECISIONS,
                                PRESET_NAMES, RAY_SAMPLINGS, RENDER_SEMANTICS, SIGMA_READINGS, SUPERVISION_MODES,
                                VOXEL_WEIGHTINGS, supervision_parts)
from occflownet.cli import build_parser
from occflownet.commands.train import config_from_args
from occflownet.options import config_argv
from occflownet.quickstart import QUICK_RENDERING, QuickstartConfig, train_argv, train_config
from occflownet.train.recipe import PRESET_RECIPES, TrainConfig

REPO = Path(__file__).resolve().parents[1]
SETS = {"PRESET_NAMES": ("tiny", "small", "base", "paper"), "HEAD_INITS": ("prior", "official"),
        "SUPERVISION_MODES": ("2d", "3d", "2d+3d"), "FLOW_MOVERS": ("idw", "nearest"),
        "SIGMA_READINGS": ("density", "opacity"), "RENDER_SEMANTICS": ("mixture", "normalized"),
        "LR_SCHEDULES": ("constant", "cosine"), "INT8_RANGES": ("reduced", "full"),
        "PRECISIONS": ("auto", "bf16", "fp32"), "FREE_STRETCH_RULES": ("fraction", "points"),
        "RAY_SAMPLINGS": ("uniform", "sqrt-balanced"), "VOXEL_WEIGHTINGS": ("none", "sqrt-balanced")}


def test_the_sets_of_choices():
    assert {name: getattr(choices, name) for name in SETS} == SETS
    assert [sorted(supervision_parts(m)) for m in SUPERVISION_MODES] == [["2d"], ["3d"], ["2d", "3d"]]
    with pytest.raises(ValueError, match="supervision must be one of"):
        supervision_parts("4d")


def test_configs_and_checks_read_the_one_definition():
    from occflownet.model import presets
    from occflownet.render import occupancy_flow

    assert tuple(presets.PRESETS) == PRESET_NAMES == tuple(PRESET_RECIPES)
    assert presets.HEAD_INITS is HEAD_INITS and occupancy_flow.MOVERS is FLOW_MOVERS
    for bad, message in (({"flow_mover": "bilinear"}, "flow_mover must be one of"),
                         ({"head_init": "zeros"}, "head_init must be one of"),
                         ({"supervision": "4d"}, "supervision must be one of"),
                         ({"precision": "fp16"}, "precision must be one of"),
                         ({"free_stretch": "half"}, "free_stretch must be one of"),
                         ({"preset": "huge"}, "unknown preset")):
        with pytest.raises(ValueError, match=message):
            TrainConfig(**bad)


def _choices_of(verb: str) -> dict[str, tuple]:
    sub = next(a for a in build_parser()._actions if a.dest == "verb").choices[verb]
    return {a.dest: tuple(a.choices) for a in sub._actions if a.choices}


def test_the_command_lines_offer_the_same_choices():
    assert _choices_of("train") == {"preset": PRESET_NAMES, "supervision": SUPERVISION_MODES,
                                    "flow_mover": FLOW_MOVERS, "head_init": ("", *HEAD_INITS),
                                    "sigma_is": SIGMA_READINGS, "render_semantics": RENDER_SEMANTICS,
                                    "lr_schedule": LR_SCHEDULES, "precision": PRECISIONS,
                                    "free_stretch": FREE_STRETCH_RULES, "ray_sampling": RAY_SAMPLINGS,
                                    "voxel_weighting": VOXEL_WEIGHTINGS}
    assert _choices_of("quickstart") == {"preset": PRESET_NAMES, "supervision": SUPERVISION_MODES}
    for verb in ("export", "predict"):
        assert _choices_of(verb)["preset"] == PRESET_NAMES
    assert _choices_of("export")["int8_range"] == INT8_RANGES


def _sources():
    for folder in ("occflownet", "export", "serve", "benchmarks"):
        for path in sorted((REPO / folder).rglob("*.py")):
            yield str(path.relative_to(REPO)), path


def test_no_second_spelling_of_a_set_of_choices():
    """No tuple, list or set literal of a whole set outside occflownet/choices.py, and no two supervision modes
    listed together (what a mode combines is ``supervision_parts``'s answer). A subset of the presets or movers is
    a selection (bench_inference's default presets), not a second definition."""
    spelled = {name: set(values) for name, values in SETS.items()}
    hits = []
    for rel, path in _sources():
        if rel == "occflownet/choices.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and len(node.elts) >= 2 \
                    and all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts):
                values = {e.value for e in node.elts}
                hits += [f"{rel}:{node.lineno} {name}" for name, s in spelled.items()
                         if values == s or (name == "SUPERVISION_MODES" and values <= s)]
    assert not hits, hits


def _parse_train(argv: list[str]) -> TrainConfig:
    return config_from_args(build_parser().parse_args(argv))


def _other_value(f: dataclasses.Field, value):
    """A valid value of field ``f`` that is not ``value``."""
    options = f.metadata.get("choices")
    if options:
        return next(o for o in reversed(options) if o != value)
    if isinstance(value, bool):
        return not value
    if f.name in ("rays_per_step", "warmup_steps", "checkpoint_every", "free_rays_per_step", "horizon"):
        return 7
    if f.name in ("lr", "ema_decay", "threshold", "time_limit_s", "density_scale", "free_space_weight",
                  "weight_decay", "grad_clip", "render_depth_weight", "lidar_depth_weight", "free_prior_weight",
                  "density_logit_clip", "density_grad_floor", "point_semantics_weight", "point_density_weight"):
        return 0.125
    if isinstance(value, int):
        return value + 3
    return f"x-{f.name}"


def test_every_train_config_field_is_reachable_from_the_command_line():
    default = TrainConfig(preset="tiny")
    changed = TrainConfig(**{f.name: _other_value(f, getattr(default, f.name)) for f in dataclasses.fields(default)})
    assert all(getattr(changed, f.name) != getattr(default, f.name) for f in dataclasses.fields(default))
    argv = ["train", *config_argv(changed, TrainConfig(preset=changed.preset), always=("preset",))]
    assert _parse_train(argv) == changed
    assert "--time-limit" in argv and "--precision" in argv and "--grad-clip" in argv


@pytest.mark.parametrize("cfg", [QuickstartConfig(), QuickstartConfig(supervision="3d"),
                                 QuickstartConfig(supervision="2d", voxel_mask=False, train_minutes=0.05,
                                                  max_steps=2, seed=4)])
def test_the_quickstarts_train_command_parses_to_the_config_it_runs(cfg, tmp_path):
    train_cfg = train_config(cfg, tmp_path / "world", tmp_path / "run", "v1.0-trainval")
    argv = train_argv(train_cfg)
    assert argv[0] == "train" and argv[-1] == "--resume"
    parsed = build_parser().parse_args(shlex.split(shlex.join(argv)))
    assert parsed.resume and config_from_args(parsed) == train_cfg
    assert train_cfg.time_limit_s == cfg.train_minutes * 60
    rendering = {name: getattr(train_cfg, name) for name in QUICK_RENDERING}
    assert (rendering == QUICK_RENDERING) == train_cfg.uses_2d           # the rendering recipe when rays render


def test_every_quickstart_field_is_reachable_from_the_command_line():
    from occflownet.commands.quickstart import QuickstartConfig as Used
    from occflownet.options import config_kwargs

    changed = QuickstartConfig(out="elsewhere", scenes=5, frames=4, seed=2, train_minutes=0.5, max_steps=9,
                               supervision="2d", voxel_mask=False)
    argv = ["quickstart", *config_argv(changed, QuickstartConfig())]
    assert Used(**config_kwargs(build_parser().parse_args(argv), Used)) == changed
    assert len(argv) == 1 + 2 * 7 + 1                                     # every field changed, every one given
