"""The README's main job, end to end on a very small world and budget: every stage runs and leaves its artifact."""
import json
import shlex

import numpy as np

from occflownet.cli import build_parser, main
from occflownet.commands.train import config_from_args
from occflownet.train.recipe import TrainConfig


def test_quickstart_small(tmp_path, capsys):
    out = tmp_path / "qs"
    assert main(["quickstart", "--out", str(out), "--scenes", "2", "--frames", "3", "--train-minutes", "0.05",
                 "--max-steps", "2"]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "quickstart finished" in printed and "occflownet serve --model" in printed
    # the announced train command, run again, is the run that trained: the same train_config.json
    announced = next(line for line in captured.err.splitlines() if line.startswith("[3/5] occflownet train "))
    again = config_from_args(build_parser().parse_args(shlex.split(announced.split(" ", 2)[2])))
    assert again == TrainConfig.from_dict(json.loads((out / "run" / "train_config.json").read_text()))
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
