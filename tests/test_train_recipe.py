"""Named recipes: a run is built from a name (occflownet/train/recipes.py), explicit options win over the recipe's
values, a recorded run reruns from its train_config.json, `paper` is the run the paper's settings gave before
recipes existed, every recipe trains, and what a step loads follows from the loss terms (losses.INPUT_DATA)."""
import ast
import dataclasses
import json
from pathlib import Path

import pytest

from occflownet.cli import build_parser
from occflownet.commands.train import config_from_args, describe
from occflownet.train.recipe import EXPERIMENTAL, GROUPS, RECIPE_GROUPS, TrainConfig
from occflownet.train.recipes import DEFAULT_RECIPE, PRESET_SCHEDULES, RECIPES, ladder, recipe

REPO = Path(__file__).resolve().parents[1]
# The configuration `occflownet train --preset tiny` ran before recipes existed (the paper's settings), as its
# train_config.json recorded it.
PAPER_BEFORE = json.loads((REPO / "tests" / "data" / "paper_default_train_config.json").read_text())


def _parse(*argv: str) -> TrainConfig:
    return config_from_args(build_parser().parse_args(["train", *argv]))


def test_every_recipe_is_a_valid_named_configuration():
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    for name, r in RECIPES.items():
        assert r.name == name and r.description and r.supervises and r.source.startswith("docs/")
        assert set(r.settings) <= names, name
        cfg = TrainConfig.from_recipe(name)
        assert cfg.recipe == name and not cfg.recipe_changes()
        assert {k: getattr(cfg, k) for k in r.settings} == dict(r.settings)
    assert DEFAULT_RECIPE == "recommended" and sorted(ladder()) == list(range(1, 10))
    with pytest.raises(ValueError, match="unknown recipe 'best'"):
        recipe("best")


def test_the_recommended_recipe_is_what_the_measurements_recommend():
    cfg = TrainConfig.from_recipe("recommended")
    assert (cfg.supervision, cfg.horizon, cfg.flow, cfg.flow_mover) == ("2d", 3, True, "nearest")
    assert cfg.free_before_point and cfg.free_beyond_grid and cfg.box_line_of_sight and cfg.free_stretch == "points"
    assert cfg.point_semantics_weight == cfg.point_density_weight == 1.0 and cfg.free_prior_weight == 2.0
    assert cfg.render_depth_weight == 0.0 and cfg.ray_sampling == "sqrt-balanced"


def test_paper_is_the_run_the_papers_settings_gave_before_recipes():
    recorded = TrainConfig.from_dict(PAPER_BEFORE)            # options since removed, recorded at their off value
    assert TrainConfig.from_recipe("paper", dataroot="", out="runs/tiny") == recorded
    assert TrainConfig() == recorded                            # the dataclass's defaults are the paper's
    with pytest.raises(ValueError, match="density_logit_clip"):
        TrainConfig.from_dict({**PAPER_BEFORE, "density_logit_clip": 6.0})   # a removed option that was in use


def test_options_given_win_over_the_recipe(prepared_synth_root, tmp_path):
    root, version = prepared_synth_root
    base = ["--dataroot", str(root), "--out", str(tmp_path)]
    assert _parse(*base) == TrainConfig.from_recipe(DEFAULT_RECIPE, dataroot=str(root), out=str(tmp_path),
                                                    version=version)
    cfg = _parse(*base, "--recipe", "paper-flow", "--no-flow", "--lr", "0.001", "--preset", "base")
    assert (cfg.recipe, cfg.flow, cfg.lr, cfg.preset) == ("paper-flow", False, 0.001, "base")
    assert cfg.rays_per_step == PRESET_SCHEDULES["base"]["rays_per_step"]     # the preset's, not tiny's
    assert cfg.recipe_changes() == {"flow": (True, False), "lr": (1e-4, 0.001)}
    assert "not a measured recipe" in describe(cfg) and "not a measured" not in describe(_parse(*base))
    with pytest.raises(SystemExit):
        _parse(*base, "--horizon", "-1")                                       # below the field's minimum


def test_a_recorded_run_reruns_from_its_config(prepared_synth_root, tmp_path):
    root, version = prepared_synth_root
    cfg = TrainConfig.from_recipe("quickstart", dataroot=str(root), out=str(tmp_path / "a"), version=version,
                                  lr=3e-3, seed=5)
    path = tmp_path / "train_config.json"
    path.write_text(json.dumps(cfg.to_dict()))
    assert _parse("--config", str(path)) == cfg
    again = _parse("--config", str(path), "--out", str(tmp_path / "b"), "--max-steps", "7")
    assert again == dataclasses.replace(cfg, out=str(tmp_path / "b"), max_steps=7)
    with pytest.raises(ValueError, match="--recipe or --config"):
        _parse("--config", str(path), "--recipe", "paper")
    with pytest.raises(FileNotFoundError, match="missing.json"):
        _parse("--config", str(tmp_path / "missing.json"))


def test_help_lists_few_options_outside_the_experimental_group():
    sub = next(a for a in build_parser()._actions if a.dest == "verb").choices["train"]
    titles = [g.title for g in sub._action_groups]
    assert [t for t, _ in GROUPS] == [t for t in titles if t in dict(GROUPS)]
    main = [a for g in sub._action_groups if g.title != EXPERIMENTAL for a in g._group_actions if a.dest != "help"]
    assert len(main) <= 25, [a.dest for a in main]
    assert {f.metadata["group"] for f in dataclasses.fields(TrainConfig)} == {t for t, _ in GROUPS}


def test_fields_are_checked_from_their_metadata():
    checked = 0
    for f in dataclasses.fields(TrainConfig):
        if f.metadata.get("minimum") is not None:
            with pytest.raises(ValueError, match=f"{f.name} must be at least"):
                TrainConfig(**{f.name: f.metadata["minimum"] - 1})
            checked += 1
    assert checked >= 15


def _spelled_fields(node) -> set[str]:
    """The recipe fields a dict literal or a call's keywords set to written-out values, or a list of option
    strings sets."""
    fields = {f.name for f in dataclasses.fields(TrainConfig) if f.metadata["group"] in RECIPE_GROUPS}
    flags = {"--" + f.replace("_", "-"): f for f in fields} | {"--no-" + f.replace("_", "-"): f for f in fields}
    literal = (ast.Constant, ast.UnaryOp)          # a value written out (-1 is a UnaryOp), not one passed through
    if isinstance(node, ast.Dict):
        return {k.value for k, v in zip(node.keys, node.values)
                if isinstance(k, ast.Constant) and k.value in fields and isinstance(v, literal)}
    if isinstance(node, ast.Call):
        return {k.arg for k in node.keywords if k.arg in fields and isinstance(k.value, literal)}
    if isinstance(node, (ast.List, ast.Tuple)):
        return {flags[e.value] for e in node.elts if isinstance(e, ast.Constant) and e.value in flags}
    return set()


def test_no_recipe_is_spelled_outside_the_registry():
    """No dict, call or option list outside occflownet/train/recipes.py sets two or more of the fields a recipe is
    made of: a named configuration is spelled once, and the code and the benchmarks read it by name."""
    hits = []
    for folder in ("occflownet", "export", "serve", "benchmarks"):
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = str(path.relative_to(REPO))
            if rel == "occflownet/train/recipes.py":
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                spelled = _spelled_fields(node)
                if len(spelled) >= 2:
                    hits.append(f"{rel}:{node.lineno} {sorted(spelled)}")
    assert not hits, hits


# What a step of each kind of recipe loads, by hand from the loss terms it has.
EXPECTED_DATA = {
    "recommended": {"rays", "free_rays", "depth_points", "class_counts"},
    "paper": {"rays", "depth_points", "class_counts"},
    "paper-semantics": {"rays"},
    "paper-3d": {"voxel_labels", "depth_points"},
    "quickstart": {"rays", "free_rays", "voxel_labels", "depth_points"},
    "quickstart-3d": {"voxel_labels", "depth_points"},
}


@pytest.mark.parametrize("name", sorted(EXPECTED_DATA))
def test_a_step_loads_what_its_loss_terms_read(name, prepared_synth_root):
    from occflownet.data.flow import flow_path, load_flow_records
    from occflownet.data.index import load_index
    from occflownet.train.dataset import TrainingSamples
    from occflownet.train.losses import loss_terms, step_data

    root, version = prepared_synth_root
    cfg = TrainConfig.from_recipe(name, dataroot=str(root), version=version)
    assert step_data(loss_terms(cfg)) == EXPECTED_DATA[name]
    index = load_index(root, version)
    flow = load_flow_records(flow_path(root, version)) if cfg.flow else None
    item = TrainingSamples(root, index, index.split_positions("train"), cfg, flow)[(0, 0)]
    loaded = {"rays": "ray_origins", "free_rays": "free_origins", "depth_points": "depth_points",
              "voxel_labels": "occ_semantics"}
    assert {kind for kind, key in loaded.items() if key in item} == EXPECTED_DATA[name] - {"class_counts"}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(RECIPES))
def test_every_recipe_trains_two_steps(name, prepared_synth_root, tmp_path):
    from occflownet.train.loop import train
    from occflownet.train.losses import loss_terms

    root, version = prepared_synth_root
    cfg = TrainConfig.from_recipe(name, dataroot=str(root), version=version, out=str(tmp_path), max_steps=2,
                                  log_every=1, num_workers=0)
    train(cfg, progress=False)
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    terms = [t.name for t in loss_terms(cfg)]
    assert [r["step"] for r in log] == [1, 2] and all(set(terms) <= set(r) for r in log)
    assert all(abs(r["loss"]) < float("inf") for r in log)
    assert json.loads((tmp_path / "train_config.json").read_text())["recipe"] == name


@pytest.mark.slow
def test_recipe_paper_on_the_command_line_trains_as_the_recorded_paper_run(prepared_synth_root, tmp_path):
    """Losses bit-equal at every step: the same configuration, trained in the same order by construction."""
    from occflownet.cli import main
    from occflownet.train.loop import train

    root, version = prepared_synth_root
    run = {"dataroot": str(root), "version": version, "max_steps": 3, "log_every": 1, "num_workers": 0}
    train(TrainConfig.from_dict({**PAPER_BEFORE, **run, "out": str(tmp_path / "recorded")}), progress=False)
    argv = [f"--{k.replace('_', '-')}={v}" for k, v in run.items()]
    assert main(["train", "--recipe", "paper", *argv, "--out", str(tmp_path / "cli"), "--quiet"]) == 0
    logs = [[json.loads(line) for line in (tmp_path / d / "log.jsonl").read_text().splitlines()]
            for d in ("recorded", "cli")]
    keys = ("loss", "render_depth", "render_semantics", "lidar_depth", "grad_norm", "lr")
    assert [[r[k] for k in keys] for r in logs[0]] == [[r[k] for k in keys] for r in logs[1]]
