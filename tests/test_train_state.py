"""TrainingState: save and load are mirror images, the file is a model checkpoint, resumes check the recipe."""
import pytest
import torch

from occflownet.model import get_preset, load_checkpoint
from occflownet.train.recipe import TrainConfig
from occflownet.train.state import TRAIN_KEYS, TrainingError, TrainingState


def _trained_state(tmp_path, steps=2) -> TrainingState:
    """A tiny state after ``steps`` optimiser steps on a made-up loss (no data needed)."""
    cfg = TrainConfig(preset="tiny", out=str(tmp_path), lr=1e-3, warmup_steps=4)
    state = TrainingState.create(cfg, get_preset("tiny", threshold=0.3), "cpu")
    for _ in range(steps):
        loss = sum((p.float() ** 2).mean() for p in state.model.parameters())
        state.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        state.optimizer.step()
        state.scheduler.step()
        state.ema.update(state.model)
        state.step += 1
    return state


def _assert_same_tensors(a: dict, b: dict):
    """Exact: a save and a load copy the tensors (no arithmetic)."""
    assert set(a) == set(b)
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_save_then_load_restores_every_part(tmp_path):
    state = _trained_state(tmp_path)
    path = state.save(tmp_path / "checkpoints" / "last.pt")
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]           # atomic: no temp file left
    rng = torch.get_rng_state()
    torch.manual_seed(123)
    back = TrainingState.load(path)
    assert torch.equal(torch.get_rng_state(), rng)
    assert back.cfg == state.cfg and back.model_cfg == state.model_cfg and back.step == 2
    _assert_same_tensors(back.model.state_dict(), state.model.state_dict())
    assert back.ema.state_dict()["updates"] == state.ema.updates and back.ema.decay == state.cfg.ema_decay
    _assert_same_tensors(back.ema.state_dict()["shadow"], state.ema.state_dict()["shadow"])
    assert back.scheduler.state_dict() == state.scheduler.state_dict()
    saved, restored = state.optimizer.state_dict(), back.optimizer.state_dict()
    assert saved["param_groups"] == restored["param_groups"]
    for i, s in saved["state"].items():
        _assert_same_tensors(s, restored["state"][i])
    # one more save of the restored state writes the same training dict
    again = back.save(tmp_path / "again.pt")
    a, b = (torch.load(p, weights_only=True) for p in (path, again))
    assert set(a["extra"]["train"]) == set(b["extra"]["train"]) == set(TRAIN_KEYS)
    assert a["extra"]["train"]["config"] == b["extra"]["train"]["config"] and a["config"] == b["config"]


def test_the_checkpoint_is_a_model_checkpoint_of_the_ema_weights(tmp_path):
    state = _trained_state(tmp_path)
    path = state.save(tmp_path / "last.pt")
    model, model_cfg, extra = load_checkpoint(path, expect_preset="tiny")
    assert model_cfg == state.model_cfg
    _assert_same_tensors(model.state_dict(), state.ema.shadow.state_dict())
    assert extra["train"]["step"] == 2
    assert not all(torch.equal(v, state.model.state_dict()[k]) for k, v in model.state_dict().items())


def test_resume_may_change_only_how_long_and_where_it_runs(tmp_path):
    state = _trained_state(tmp_path)
    path = state.save(tmp_path / "last.pt")
    longer = TrainConfig(**{**state.cfg.to_dict(), "max_steps": 5000, "time_limit_s": 60.0, "num_workers": 0})
    assert TrainingState.load(path, cfg=longer).cfg == longer
    other = TrainConfig(**{**state.cfg.to_dict(), "lr": 5e-4, "supervision": "3d"})
    with pytest.raises(TrainingError, match=r"last\.pt was trained with supervision='2d', lr=0\.001"):
        TrainingState.load(path, cfg=other)


def test_a_model_only_checkpoint_cannot_be_resumed(tmp_path):
    from occflownet.model import save_checkpoint

    state = _trained_state(tmp_path, steps=0)
    path = save_checkpoint(tmp_path / "weights.pt", state.model, state.model_cfg)
    with pytest.raises(TrainingError, match=r"weights\.pt: not a training checkpoint"):
        TrainingState.load(path)


def test_lr_schedules_warm_up_then_hold_or_decay_to_zero_at_the_last_step():
    from occflownet.train.schedule import lr_factor

    assert [lr_factor(s, 4) for s in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]           # official: constant
    cosine = [lr_factor(s, 4, "cosine", 10) for s in range(10)]
    assert cosine[:4] == [0.25, 0.5, 0.75, 1.0]                                               # the same warm-up
    assert cosine[6] == pytest.approx(0.5) and cosine[-1] == pytest.approx(0.0, abs=1e-12)    # half-way, the end
    assert all(a > b for a, b in zip(cosine[3:], cosine[4:]))                                 # decays
    with pytest.raises(ValueError, match="lr schedule must be one of"):
        lr_factor(0, 4, "step")
    cfg = TrainConfig(preset="tiny", lr=1e-3, warmup_steps=4, max_steps=10, lr_schedule="cosine")
    state = TrainingState.create(cfg, get_preset("tiny"), "cpu")
    rates = []
    for _ in range(10):
        rates.append(state.optimizer.param_groups[0]["lr"])
        state.optimizer.step()
        state.scheduler.step()
    assert rates == pytest.approx([1e-3 * f for f in cosine])
