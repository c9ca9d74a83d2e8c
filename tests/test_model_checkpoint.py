import pytest
import torch

from occflownet.model import CheckpointError, create_model, get_preset, load_checkpoint, save_checkpoint


def test_round_trip_keeps_weights_config_and_extra(tmp_path):
    cfg = get_preset("tiny", threshold=0.3)
    model = create_model(cfg, seed=1)
    extra = {"step": 12, "optimizer": {"state": {0: {"exp_avg": torch.ones(3)}}, "lr": 1e-4}, "note": "x",
             "ema": {"backbone.conv1.weight": torch.zeros(2)}, "flags": [True, None]}
    path = save_checkpoint(tmp_path / "run" / "last.pt", model, cfg, extra)
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]          # no temp file left
    loaded, cfg2, extra2 = load_checkpoint(path, expect_preset="tiny")
    assert cfg2 == cfg and cfg2.threshold == 0.3
    assert not loaded.training
    sd = model.state_dict()
    # exact: a save and a load copy the tensors (no arithmetic)
    assert all(torch.equal(v, sd[k]) for k, v in loaded.state_dict().items())
    assert extra2["step"] == 12 and torch.equal(extra2["optimizer"]["state"][0]["exp_avg"], torch.ones(3))
    raw = torch.load(path, weights_only=True)
    assert set(raw) == {"state_dict", "config", "occflownet_version", "extra"}


def test_wrong_preset_names_the_file(tmp_path):
    path = save_checkpoint(tmp_path / "tiny.pt", create_model(get_preset("tiny")), get_preset("tiny"))
    with pytest.raises(CheckpointError, match=r"tiny\.pt.*preset 'tiny', expected 'base'"):
        load_checkpoint(path, expect_preset="base")


def test_corrupt_and_truncated_files_name_the_file(tmp_path):
    path = save_checkpoint(tmp_path / "good.pt", create_model(get_preset("tiny")), get_preset("tiny"))
    data = path.read_bytes()
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated.pt"):
        load_checkpoint(truncated)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00" * 100)
    with pytest.raises(CheckpointError, match="garbage.pt"):
        load_checkpoint(garbage)
    with pytest.raises(CheckpointError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.ones(1)}, other)
    with pytest.raises(CheckpointError, match="other.pt"):
        load_checkpoint(other)


def test_mismatched_weights_are_reported(tmp_path):
    cfg = get_preset("tiny")
    path = save_checkpoint(tmp_path / "m.pt", create_model(cfg), cfg)
    payload = torch.load(path, weights_only=True)
    payload["config"]["neck_channels"] = 32
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="m.pt"):
        load_checkpoint(path)
