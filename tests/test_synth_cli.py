"""`occflownet synth` from the command line: writes the layout and previews, refuses bad input clearly."""
import cv2

from occflownet.cli import main


def test_synth_command_writes_dataset_and_previews(tmp_path, capsys):
    out = tmp_path / "w"
    args = ["synth", "--out", str(out), "--scenes", "1", "--frames", "2", "--seed", "1", "--width", "96",
            "--height", "54", "--margin", "50", "--preview", "--no-progress"]
    assert main(args) == 0
    assert "wrote 2 keyframes" in capsys.readouterr().out
    assert (out / "v1.0-trainval" / "sample.json").is_file() and (out / "v1.0-trainval" / "splits.json").is_file()
    previews = sorted((out / "preview").glob("*.png"))
    assert len(previews) == 2
    img = cv2.imread(str(previews[0]))
    assert img.shape == (2 * 54 + 50, 3 * 96 + 2 * 54, 3)   # two camera rows over a two-row class legend
    assert len(list((out / "samples" / "CAM_FRONT").glob("*.jpg"))) == 2
    # an existing dataset is not overwritten silently
    assert main(args) == 2
    assert "already holds a dataset" in capsys.readouterr().err
    assert main(args + ["--overwrite", "--version", "v1.0-mini"]) == 0
    assert (out / "v1.0-mini" / "scene.json").is_file()


def test_val_frames_sets_the_val_scene_keyframes(tmp_path, capsys):
    import json

    out = tmp_path / "w"
    assert main(["synth", "--out", str(out), "--scenes", "3", "--frames", "1", "--val-frames", "2", "--seed", "1",
                 "--width", "96", "--height", "54", "--margin", "50", "--no-progress"]) == 0
    assert "wrote 4 keyframes in 3 scene(s)" in capsys.readouterr().out
    tables = out / "v1.0-trainval"
    scenes = json.loads((tables / "scene.json").read_text())
    assert [s["nbr_samples"] for s in scenes] == [1, 1, 2]
    splits = json.loads((tables / "splits.json").read_text())
    assert splits == {"train": [scenes[0]["name"], scenes[1]["name"]], "val": [scenes[2]["name"]]}
    assert len(json.loads((tables / "sample.json").read_text())) == 4
    assert len(list((out / "gts").glob("*/*/labels.npz"))) == 4


def test_val_scenes_makes_the_last_scenes_the_val_split(tmp_path, capsys):
    import json

    out = tmp_path / "w"
    assert main(["synth", "--out", str(out), "--scenes", "4", "--frames", "2", "--val-scenes", "2", "--val-frames",
                 "1", "--seed", "1", "--width", "96", "--height", "54", "--margin", "50", "--no-progress"]) == 0
    assert "wrote 6 keyframes in 4 scene(s)" in capsys.readouterr().out
    tables = out / "v1.0-trainval"
    scenes = json.loads((tables / "scene.json").read_text())
    names = [s["name"] for s in scenes]
    assert [s["nbr_samples"] for s in scenes] == [2, 2, 1, 1]
    assert json.loads((tables / "splits.json").read_text()) == {"train": names[:2], "val": names[2:]}
    # no more scenes than --val-scenes: every scene in both splits, each with --frames keyframes
    out = tmp_path / "v"
    assert main(["synth", "--out", str(out), "--scenes", "2", "--frames", "1", "--val-scenes", "2", "--val-frames",
                 "3", "--seed", "1", "--width", "96", "--height", "54", "--margin", "50", "--no-progress"]) == 0
    tables = out / "v1.0-trainval"
    scenes = json.loads((tables / "scene.json").read_text())
    assert [s["nbr_samples"] for s in scenes] == [1, 1]
    names = [s["name"] for s in scenes]
    assert json.loads((tables / "splits.json").read_text()) == {"train": names, "val": names}


def test_synth_command_rejects_bad_options(tmp_path, capsys):
    import pytest

    base = ["synth", "--out", str(tmp_path / "x"), "--no-progress"]
    for bad, message in ((["--margin", "10"], "--margin must be at least 45"),
                         (["--frames", "0"], "--frames must be at least 1")):
        with pytest.raises(SystemExit) as refused:                 # refused by the parser, from the fields' minimum
            main(base + bad)
        assert refused.value.code == 2 and message in capsys.readouterr().err
    assert main(base + ["--lanes", "3", "1"]) == 2                  # refused by WorldConfig: MIN <= MAX
    assert "lanes (MIN, MAX) must satisfy" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_world_config_checks_its_own_ranges():
    """The ranges live in the library (WorldConfig), so Python callers get the same checks as the command line."""
    import pytest

    from occflownet.synth.layout import WorldConfig

    for bad in ({"margin": 10.0}, {"lanes": (3, 1)}, {"ego_speed": (5.0, 30.0)}, {"traffic": 0.0},
                {"cross_street_probability": 1.5}):
        with pytest.raises(ValueError):
            WorldConfig(**bad)
