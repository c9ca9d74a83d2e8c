"""The benchmarks' shared parts with known answers: the order in which the harness runs two sides, its JSON lines,
the options that give a recipe to a tree with or without the recipe registry, the studies' run selection
(recipes by name, ladder rows, the recommended rendering added) and the near-miss IoU of ``near_misses``."""
import argparse
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))                     # the benchmarks package, when pytest runs from elsewhere

from benchmarks import harness  # noqa: E402
from benchmarks.studies import ablation, near_misses  # noqa: E402
from occflownet.eval.metrics import iou_from_confusion  # noqa: E402
from occflownet.occ3d import FREE  # noqa: E402
from occflownet.cli import build_parser  # noqa: E402
from occflownet.commands.train import config_from_args  # noqa: E402
from occflownet.train.recipe import TrainConfig  # noqa: E402
from occflownet.train.recipes import RECIPE_NAMES, ladder  # noqa: E402

RUN = {"dataroot": "D", "out": "O", "version": "v1.0-trainval"}


def _parsed(options: list[str]) -> TrainConfig:
    """The TrainConfig today's ``occflownet train`` makes of ``options`` (with RUN's data and output)."""
    args = build_parser().parse_args(["train", *options, *(f"--{k}={v}" for k, v in RUN.items())])
    return config_from_args(args)


def _without_recipe(cfg: TrainConfig) -> dict:
    return {k: v for k, v in cfg.to_dict().items() if k != "recipe"}


def test_interleaved_runs_the_sides_in_turn_reversing_every_other_round():
    calls = []
    runs = harness.interleaved({"a": lambda: calls.append("a") or 1, "b": lambda: calls.append("b") or 2}, 3)
    assert calls == ["a", "b", "b", "a", "a", "b"]
    assert [v for _, v in runs["a"]] == [1, 1, 1] and [v for _, v in runs["b"]] == [2, 2, 2]
    assert all(seconds >= 0 for v in runs.values() for seconds, _ in v)


def test_results_are_appended_as_json_lines_with_the_machine_state(tmp_path, capsys):
    path = tmp_path / "out" / "results.jsonl"
    results = harness.Results("demo", path, matmul_seconds=0.01)
    results.add({"x": 1}, "| row | 1 |")
    results.add({"x": 2}, "two")
    records = harness.read_jsonl(path)
    assert [r["x"] for r in records] == [1, 2] and {r["benchmark"] for r in records} == {"demo"}
    assert all("load_average" in r and "matmul_gflops" in r for r in records)
    table_row, line = capsys.readouterr().out.splitlines()
    assert table_row.startswith("| row | 1 | load ") and table_row.endswith(" |")      # the state as one more cell
    assert line.startswith("two  [load ")
    assert harness.read_jsonl(tmp_path / "missing.jsonl") == []


@pytest.mark.parametrize("name", RECIPE_NAMES)
def test_a_recipe_is_given_to_a_tree_without_the_registry_as_its_settings(name, monkeypatch):
    """Parsed over the paper's settings (the defaults of a tree older than the registry), the options are the
    recipe; a tree with a registry that lacks the name gets them after --recipe paper; this checkout gets --recipe."""
    assert harness.recipe_argv(name) == ["--recipe", name]
    monkeypatch.setattr(harness, "tree_recipes", lambda tree: ())
    settings = harness.recipe_argv(name, Path("old-tree"))
    assert "--recipe" not in settings
    assert _without_recipe(_parsed(["--recipe", "paper", *settings])) == \
        _without_recipe(TrainConfig.from_recipe(name, **RUN))
    monkeypatch.setattr(harness, "tree_recipes", lambda tree: ("paper",))
    assert harness.recipe_argv(name, Path("newer-tree")) == (["--recipe", name] if name == "paper"
                                                           else ["--recipe", "paper", *settings])


def _runs(*argv: str, default: str | None = None):
    ap = argparse.ArgumentParser()
    ablation.add_run_options(ap, default)
    return ablation.selected_runs(ap, ap.parse_args(list(argv)), default)


def test_the_ladder_with_the_recommended_rendering():
    runs = {r.recipe: r for r in _runs("--rows", "1,5,6", "--rendering")}
    assert list(runs) == [ladder()[1].name, ladder()[5].name, ladder()[6].name]
    assert runs["paper-3d"].options == ("--recipe", "paper-3d") and runs["paper-3d"].variant == "recipe"
    assert runs["paper"].variant == runs["paper-flow"].variant == "rendering"
    # row 6 with the rendering is the recommended recipe without its image term (not a part of the paper's ladder);
    # row 5 with it is the paper's Base rendered so
    recommended = {**_without_recipe(TrainConfig.from_recipe("recommended", **RUN)), "image_semantics_weight": 0.0}
    assert _without_recipe(_parsed(list(runs["paper-flow"].options))) == recommended
    paper = _parsed(list(runs["paper"].options))
    assert not paper.flow and _without_recipe(paper) == {**recommended, "flow": False}


def test_runs_by_name_with_an_experiment():
    (run,) = _runs("--recipes", "quickstart", "--variant", "fp32", "--extra", "--precision fp32")
    assert (run.recipe, run.variant, run.options) == ("quickstart", "fp32", ("--recipe", "quickstart", "--precision",
                                                                            "fp32"))
    assert [r.recipe for r in _runs(default="recommended,paper-3d")] == ["recommended", "paper-3d"]
    assert [r.recipe for r in _runs()] == [r.name for _, r in sorted(ladder().items())]
    for argv in (["--rows", "1", "--recipes", "paper"], ["--extra", "--flow"], ["--rows", "10"], ["--recipes", "x"]):
        with pytest.raises(SystemExit):
            _runs(*argv)


def test_records_of_ladder_rows_read_as_their_recipes():
    assert ablation.record_key({"row": 5, "variant": "official", "seed": 1, "steps": 200}) == ("recipe", "paper", 1, 200)
    assert ablation.record_key({"row": 1, "steps": 800}) == ("recipe", "paper-3d", 0, 800)
    assert ablation.record_key({"recipe": "recommended", "variant": "x", "seed": 2, "steps": 9}) == \
        ("x", "recommended", 2, 9)


def test_a_voxel_placed_one_beside_its_label_is_a_miss_at_radius_0_and_a_hit_at_radius_1():
    label = np.full((8, 8, 4), FREE, np.uint8)
    pred = label.copy()
    label[3, 3, 1] = 4                                   # a car voxel
    pred[4, 3, 1] = 4                                    # predicted one voxel along x
    pred[0, 7, 3] = 15                                   # a manmade voxel outside the mask: not counted
    mask = np.ones(label.shape, bool)
    mask[0, 7, 3] = False
    at0 = near_misses.near_counts(pred, label, mask, 0)
    at1 = near_misses.near_counts(pred, label, mask, 1)
    assert [int(a[4]) for a in at0] == [0, 1, 1]         # hits, misses, false positives
    assert [int(a[4]) for a in at1] == [1, 0, 0]
    assert near_misses.iou(*at0)[4] == 0.0 and near_misses.iou(*at1)[4] == 1.0
    assert np.isnan(near_misses.iou(*at1)[15]) and np.isnan(near_misses.iou(*at1)[0])
    pred[6, 3, 1] = 4                                    # two voxels away: a false positive at radius 1
    assert [int(a[4]) for a in near_misses.near_counts(pred, label, mask, 1)] == [1, 0, 1]


def test_the_near_miss_iou_at_radius_0_is_the_evaluations_iou():
    rng = np.random.default_rng(0)
    label = rng.choice([0, 4, 11, 15, FREE], size=(20, 20, 8), p=[0.02, 0.1, 0.2, 0.1, 0.58]).astype(np.uint8)
    pred = np.where(rng.random(label.shape) < 0.3, rng.choice([4, 11, 15, FREE], size=label.shape), label)
    mask = rng.random(label.shape) < 0.8
    hist = np.bincount(label[mask].astype(np.int64) * 18 + pred[mask], minlength=18 * 18).reshape(18, 18)
    expected = iou_from_confusion(hist)[:FREE]
    got = near_misses.iou(*near_misses.near_counts(pred.astype(np.uint8), label, mask, 0))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got[~np.isnan(got)], expected[~np.isnan(expected)])
