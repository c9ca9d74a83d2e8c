"""The README's main job, end to end on a very small world and budget: every stage runs and leaves its artifact."""
import dataclasses
import json
import shlex

import numpy as np
import pytest

from occflownet.cli import build_parser, main
from occflownet.commands.train import config_from_args
from occflownet.options import config_kwargs
from occflownet.quickstart import QuickstartConfig, synth_settings
from occflownet.synth.generate import SynthConfig
from occflownet.train.recipe import TrainConfig


def test_quickstart_small(tmp_path, capsys):
    out = tmp_path / "qs"
    assert main(["quickstart", "--out", str(out), "--scenes", "2", "--frames", "2", "--val-frames", "3",
                 "--train-minutes", "0.05", "--max-steps", "2"]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "quickstart finished" in printed and "occflownet serve --model" in printed
    estimate = next(line for line in captured.err.splitlines() if line.startswith("quickstart: on this machine"))
    assert "GFLOP/s" in estimate and "train ~" in estimate        # what each stage should take, said first
    timings = json.loads((out / "timings.json").read_text())["seconds"]
    assert sorted(timings) == ["eval", "export", "prepare", "synth", "train"] and min(timings.values()) > 0
    # the announced train command, run again, is the run that trained: the same train_config.json
    announced = next(line for line in captured.err.splitlines() if line.startswith("[3/5] occflownet train "))
    again = config_from_args(build_parser().parse_args(shlex.split(announced.split(" ", 2)[2])))
    assert again == TrainConfig.from_dict(json.loads((out / "run" / "train_config.json").read_text()))
    # the announced synth command writes the world it wrote: parsed again, the settings it gave generate
    announced = next(line for line in captured.err.splitlines() if line.startswith("[1/5] occflownet synth "))
    words = shlex.split(announced.split(" ", 2)[2])
    given = SynthConfig(**config_kwargs(build_parser().parse_args(words[:words.index("(then")]), SynthConfig))
    assert given == synth_settings(QuickstartConfig(scenes=2, frames=2, val_frames=3))
    assert (given.scenes, given.frames, given.val_scenes, given.val_frames, given.preview) == (2, 2, 1, 3, True)
    result = json.loads((out / "eval.json").read_text())
    assert result["split"] == "val" and result["samples"] == 3
    assert (out / "model.onnx").is_file() and (out / "run" / "checkpoints" / "last.pt").is_file()
    assert len(list((out / "predictions").glob("*.npz"))) == 3
    import cv2

    picture = cv2.imread(str(out / "side_by_side.png"))      # ground truth beside the prediction
    assert picture is not None and picture.shape[1] == 1200 and "side_by_side.png" in printed
    viewer = (out / "view.html").read_text()                   # the same keyframe in 3D, next to the picture
    assert "view.html" in printed and 'id="occ-data"' in viewer and '"ground truth"' in viewer
    assert sorted(p.name for p in (out / "example").iterdir())[:2] == ["CAM_BACK.jpg", "CAM_BACK_LEFT.jpg"]
    # the printed predict command works on the example it wrote
    assert main(["predict", "--model", str(out / "model.onnx"), "--images", str(out / "example"), "--calib",
                 str(out / "example" / "calib.json"), "--out", str(tmp_path / "grid.npz"), "--html",
                 str(tmp_path / "grid.html")]) == 0
    assert "CAM_FRONT" in (tmp_path / "grid.html").read_text()
    with np.load(tmp_path / "grid.npz") as z:
        assert z["occupancy"].shape == (200, 200, 16)


def test_the_estimate_scales_with_the_machine_and_caps_training_at_its_budget():
    from occflownet.quickstart import StageCosts, estimate_minutes
    from occflownet.train.recipes import RECIPES

    costs = StageCosts(matmul_gflops=100.0, synth_per_keyframe=2.0, prepare_per_keyframe=0.5, train_setup=6.0,
                       eval_per_keyframe=1.0, export=12.0)
    cfg = QuickstartConfig(scenes=3, frames=10, val_frames=0, train_minutes=7.0, max_steps=1000,
                           recipe="quickstart-3d")
    same = estimate_minutes(cfg, 100.0, costs)
    step = RECIPES["quickstart-3d"].step_seconds                   # a step costs its recipe's measured seconds
    assert same == pytest.approx({"synth": 1.0, "prepare": 0.25, "train": (6.0 + 1000 * step) / 60,
                                  "eval": 10 / 60, "export": 0.2})
    short = estimate_minutes(dataclasses.replace(cfg, val_frames=4), 100.0, costs)   # 2 x 10 + 4 keyframes
    assert short["synth"] == pytest.approx(24 * 2.0 / 60) and short["eval"] == pytest.approx(4 * 1.0 / 60)
    several = estimate_minutes(dataclasses.replace(cfg, val_scenes=2, val_frames=4), 100.0, costs)  # 10 + 2 x 4
    assert several["synth"] == pytest.approx(18 * 2.0 / 60) and several["eval"] == pytest.approx(8 * 1.0 / 60)
    rendering = estimate_minutes(dataclasses.replace(cfg, recipe="quickstart", max_steps=100), 100.0, costs)
    assert rendering["train"] == pytest.approx((6.0 + 100 * RECIPES["quickstart"].step_seconds) / 60)
    slower = estimate_minutes(dataclasses.replace(cfg, max_steps=3000), 50.0, costs)   # half the matmul rate ...
    assert slower["synth"] == pytest.approx(2.0) and slower["export"] == pytest.approx(0.4)
    assert slower["train"] == pytest.approx(7.0)                  # ... but training stops at its time budget


def test_quickstart_refuses_a_world_without_training_scenes(tmp_path, capsys):
    out = tmp_path / "qs"
    assert main(["quickstart", "--out", str(out), "--scenes", "3", "--val-scenes", "3"]) == 2
    assert "val_scenes (3) must be fewer than scenes (3)" in capsys.readouterr().err
    assert not out.exists()
