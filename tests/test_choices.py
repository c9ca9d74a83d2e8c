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
from occflownet.choices import FLOW_MOVERS, HEAD_INITS, INT8_RANGES, PRESET_NAMES, supervision_parts
from occflownet.cli import build_parser
from occflownet.commands.train import config_from_args
from occflownet.options import config_argv
from occflownet.quickstart import QuickstartConfig, train_argv, train_config
from occflownet.train.recipe import TrainConfig
from occflownet.train.recipes import PRESET_SCHEDULES, RECIPE_NAMES, RECIPES

REPO = Path(__file__).resolve().parents[1]
SETS = {name: value for name, value in vars(choices).items() if name.isupper() and isinstance(value, tuple)}


def test_the_sets_of_choices():
    assert len(SETS) >= 10
    for name, values in SETS.items():
        assert values and len(set(values)) == len(values) and all(isinstance(v, str) and v for v in values), name
    assert supervision_parts("2d") == {"2d"} and supervision_parts("3d") == {"3d"}
    assert supervision_parts("2d+3d") == {"2d", "3d"}
    with pytest.raises(ValueError, match="supervision must be one of"):
        supervision_parts("4d")


def test_configs_and_checks_read_the_one_definition():
    from occflownet.model import presets
    from occflownet.render import occupancy_flow

    assert tuple(presets.PRESETS) == PRESET_NAMES == tuple(PRESET_SCHEDULES)
    assert presets.HEAD_INITS is HEAD_INITS and occupancy_flow.MOVERS is FLOW_MOVERS
    checked = 0
    for f in dataclasses.fields(TrainConfig):              # every field with choices refuses a value outside them
        if f.metadata.get("choices"):
            with pytest.raises(ValueError, match=f"{f.name} must be one of"):
                TrainConfig(**{f.name: "no-such-choice"})
            checked += 1
    assert checked >= 8


def _choices_of(verb: str) -> dict[str, tuple]:
    sub = next(a for a in build_parser()._actions if a.dest == "verb").choices[verb]
    return {a.dest: tuple(a.choices) for a in sub._actions if a.choices}


def test_the_command_lines_offer_the_same_choices():
    for verb, cls in (("train", TrainConfig), ("quickstart", QuickstartConfig)):
        assert _choices_of(verb) == {f.name: tuple(f.metadata["choices"]) for f in dataclasses.fields(cls)
                                     if f.metadata.get("choices")}
    assert _choices_of("train")["recipe"] == RECIPE_NAMES
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
    spelled.pop("RECIPE_NAMES", None)
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


def _other_value(f: dataclasses.Field, value):
    """A valid value of field ``f`` that is not ``value``."""
    options = f.metadata.get("choices")
    if options:
        return next(o for o in reversed(options) if o != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, float) or f.name in ("lr", "ema_decay", "threshold"):
        return 0.125 if value != 0.125 else 0.25
    if isinstance(value, int):
        return value + 3
    return f"x-{f.name}"


def test_every_train_config_field_is_reachable_from_the_command_line():
    default = TrainConfig()
    changed = TrainConfig(**{f.name: _other_value(f, getattr(default, f.name)) for f in dataclasses.fields(default)})
    assert all(getattr(changed, f.name) != getattr(default, f.name) for f in dataclasses.fields(default))
    argv = ["train", *config_argv(changed, TrainConfig(), always=("preset",))]
    parsed = build_parser().parse_args(argv)
    given = {f.name: getattr(parsed, f.name) for f in dataclasses.fields(TrainConfig) if hasattr(parsed, f.name)}
    assert TrainConfig(**given) == changed
    assert "--time-limit" in argv and "--precision" in argv and "--grad-clip" in argv


@pytest.mark.parametrize("cfg", [QuickstartConfig(), QuickstartConfig(recipe="quickstart-3d"),
                                 QuickstartConfig(recipe="recommended", train_minutes=0.05, max_steps=2, seed=4)])
def test_the_quickstarts_train_command_parses_to_the_config_it_runs(cfg, tmp_path):
    train_cfg = train_config(cfg, tmp_path / "world", tmp_path / "run", "v1.0-trainval")
    argv = train_argv(train_cfg)
    assert argv[0] == "train" and argv[-1] == "--resume" and argv[argv.index("--recipe") + 1] == cfg.recipe
    parsed = build_parser().parse_args(shlex.split(shlex.join(argv)))
    assert parsed.resume and config_from_args(parsed) == train_cfg
    assert train_cfg.time_limit_s == cfg.train_minutes * 60
    assert train_cfg.recipe == cfg.recipe and not train_cfg.recipe_changes()   # the measured recipe, unchanged
    assert {k: getattr(train_cfg, k) for k in RECIPES[cfg.recipe].settings} == dict(RECIPES[cfg.recipe].settings)


def test_every_quickstart_field_is_reachable_from_the_command_line():
    from occflownet.commands.quickstart import QuickstartConfig as Used
    from occflownet.options import config_kwargs

    changed = QuickstartConfig(out="elsewhere", scenes=5, frames=3, val_scenes=2, val_frames=6, preset="tiny",
                               recipe="quickstart-3d", seed=2, train_minutes=0.5, max_steps=9)
    argv = ["quickstart", *config_argv(changed, QuickstartConfig())]
    assert Used(**config_kwargs(build_parser().parse_args(argv), Used)) == changed
    assert len(argv) == 1 + 2 * len(dataclasses.fields(QuickstartConfig))   # every field changed, every one given
