"""Training: the loop learns, resumes exactly after SIGKILL, trains with DDP (gloo), and fails helpfully."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from occflownet.cli import main
from occflownet.train.sampler import StepBatchSampler

FAST = ["--preset", "tiny", "--rays-per-step", "1024", "--num-workers", "0", "--log-every", "1", "--quiet"]


def _train_argv(root, out, *extra):
    return ["train", "--dataroot", str(root), "--out", str(out), "--split", "all", *FAST, *extra]


def _weights(ckpt):
    payload = torch.load(ckpt, map_location="cpu", weights_only=True)
    return payload["extra"]["train"]["model"], payload["state_dict"]


def test_step_work_counts_what_the_supervision_uses():
    """A step's work is what its batch carries: the rays it renders, the voxels its 3D loss reads (every voxel, or
    those inside mask_camera with voxel_mask: the targets' count)."""
    from occflownet.train.loop import step_work
    from occflownet.train.losses import voxel_targets

    mask = torch.zeros(200, 200, 16, dtype=torch.bool)
    mask[:10] = True                                                        # 10 * 200 * 16 = 32,000 voxels
    labels = torch.zeros(200, 200, 16, dtype=torch.uint8)
    every, masked = voxel_targets(labels), voxel_targets(labels, mask)
    rays = {"ray_depths": torch.zeros(3000)}
    assert step_work(rays) == {"rays": 3000}
    assert step_work(every) == {"voxels": 640_000}
    assert step_work(masked) == {"voxels": 32_000}
    assert step_work({**rays, **every}) == {"rays": 3000, "voxels": 640_000}
    assert step_work({"images": torch.zeros(1)}) == {}


def test_sampler_is_a_function_of_the_step_and_shards_ranks():
    a = StepBatchSampler(10, 2, seed=3, start_step=0, max_steps=12, rank=0, world_size=2)
    b = StepBatchSampler(10, 2, seed=3, start_step=0, max_steps=12, rank=1, world_size=2)
    resumed = StepBatchSampler(10, 2, seed=3, start_step=7, max_steps=12, rank=0, world_size=2)
    assert list(a)[7:] == list(resumed)
    for step in range(12):
        ia = {i for i, _ in a.keys_for_step(step)}
        ib = {i for i, _ in b.keys_for_step(step)}
        assert len(ia) == 2 and len(ib) == 2 and not ia & ib
    # one epoch (2 steps of 4 samples... here 10 samples / 4 = 2 steps) covers distinct samples
    seen = [i for s in range(a.steps_per_epoch) for i, _ in a.keys_for_step(s) + b.keys_for_step(s)]
    assert len(seen) == len(set(seen))


def _fixed_batch_loss(root, out, weights) -> dict:
    """The training loss of a fixed batch (step 0's items, fixed render jitter) under the given raw weights."""
    from occflownet.model.checkpoint import read_checkpoint
    from occflownet.model.presets import ModelConfig
    from occflownet.model.occupancy_model import create_model
    from occflownet.train.recipe import TrainConfig
    from occflownet.train.dataset import TrainingSamples, collate
    from occflownet.train import loop
    from occflownet.train.step import LossComputer

    payload = read_checkpoint(out / "checkpoints" / "last.pt")
    cfg = TrainConfig.from_dict(payload["extra"]["train"]["config"])
    model_cfg = ModelConfig.from_dict(payload["config"])
    model = create_model(model_cfg)
    model.load_state_dict(weights)
    model.train()  # batch statistics, as in training
    index, positions, flows = loop._training_data(cfg)            # the run's samples and, with flow, its records
    data = TrainingSamples(root, index, positions, cfg, flows)
    batch = collate([data[(i, 0)] for i in range(3)])
    losses = LossComputer(cfg, model_cfg, None)
    with torch.no_grad():
        outputs = model(batch["images"], batch["intrinsics"], batch["cam2ego"])
        terms = losses(outputs, batch, torch.device("cpu"), torch.Generator().manual_seed(0))
        return {k: float(v) for k, v in terms.items()}


def test_train_2d_reduces_the_loss_and_writes_a_usable_checkpoint(prepared_synth_root, tmp_path):
    # the paper's settings (rendered depth MSE and semantics, LiDAR depth): both rendered terms fall within 12 steps
    root, _ = prepared_synth_root
    out = tmp_path / "run"
    assert main(_train_argv(root, out, "--recipe", "paper", "--max-steps", "12", "--horizon", "1",
                            "--warmup-steps", "1")) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 13))
    assert {"loss", "render_depth", "render_semantics", "lidar_depth", "rays_per_s", "lr"} <= set(log[0])
    from occflownet.model.checkpoint import load_checkpoint
    from occflownet.model.occupancy_model import create_model

    model, cfg, extra = load_checkpoint(out / "checkpoints" / "last.pt")
    assert cfg.preset == "tiny" and cfg.threshold == pytest.approx(0.35)
    assert extra["train"]["step"] == 12
    initial = create_model(cfg, seed=0).state_dict()  # the run's seed is 0: the weights it started from
    before = _fixed_batch_loss(root, out, initial)
    after = _fixed_batch_loss(root, out, extra["train"]["model"])
    # measured: total 8.22 -> 5.66 (depth 5.17 -> 3.45, semantics 2.83 -> 2.72) after 12 steps
    assert after["loss"] < 0.85 * before["loss"], (before, after)
    assert after["render_depth"] < before["render_depth"] and after["render_semantics"] < before["render_semantics"]


# A run resumed in a new process continues the same run, but not bit for bit: measured on the 2-core machine, the
# resumed steps' losses lie up to 1.5e-4 (relative) from the uninterrupted run's with 2D supervision and the weights
# up to 8e-4 apart after AdamW, which amplifies rounding in small gradients; with 3D labels up to 1.4e-5 (often bit
# for bit). The cause is not found (docs/training.md, "Checkpoints, resume, failures"). A resume that uses another
# batch moves the loss by percents. A skipped or repeated step does not show in these weight bounds (early in the
# warm-up the learning rate is a few % of its 2e-3), so the counters of the optimiser state (integers: exact) and
# AdamW's second moments are checked too: exp_avg_sq sums (1 - β2) g² over every step done, so one step fewer or
# more changes it by about a sixth of its size after six steps, where rounding moves it by < 1e-3.
RESUME_TOLERANCE = {"3d": dict(atol=1e-4, loss_rtol=1e-4), "2d": dict(atol=2e-3, loss_rtol=1e-3)}
MOMENT_RTOL = 0.02
MAX_STEPS = 6


def _train_state(ckpt) -> dict:
    return torch.load(ckpt, map_location="cpu", weights_only=True)["extra"]["train"]


def assert_same_optimizer_steps(straight: dict, resumed: dict, where: str) -> None:
    """``extra.train`` of a resumed run holds the counters and the AdamW moments of the uninterrupted run's: every
    one of the MAX_STEPS steps done once (the step, the EMA's updates, the schedule and each parameter's AdamW
    step count: integers, compared exactly) and the second moments within MOMENT_RTOL (a norm ratio per tensor)."""
    counters = lambda t: {"step": t["step"], "ema_updates": t["ema_updates"],
                          "schedule": t["scheduler"]["last_epoch"],
                          "adamw": sorted({int(v["step"]) for v in t["optimizer"]["state"].values()})}
    expected = {"step": MAX_STEPS, "ema_updates": MAX_STEPS, "schedule": MAX_STEPS, "adamw": [MAX_STEPS]}
    assert counters(straight) == expected, counters(straight)
    assert counters(resumed) == expected, f"{where}: {counters(resumed)}"
    worst = max((float(torch.linalg.vector_norm(resumed["optimizer"]["state"][i]["exp_avg_sq"] - s["exp_avg_sq"])
                       / torch.linalg.vector_norm(s["exp_avg_sq"]).clamp_min(1e-30)), i)
                for i, s in straight["optimizer"]["state"].items())
    assert worst[0] < MOMENT_RTOL, f"{where}: AdamW exp_avg_sq of parameter {worst[1]} off by {worst[0]:.3g} (norm)"


@pytest.mark.parametrize("supervision", ["2d", "3d"])
def test_resume_after_sigkill_reaches_the_same_weights(prepared_synth_root, tmp_path, supervision):
    root, _ = prepared_synth_root
    common = ["--max-steps", str(MAX_STEPS), "--checkpoint-every", "2", "--supervision", supervision,
              *(["--horizon", "1", "--flow"] if supervision == "2d" else ["--horizon", "0", "--no-flow"])]
    # Every run is its own `occflownet train` process, as a user runs them, so that state left in this test process
    # by earlier tests does not decide the comparison.
    cli = [sys.executable, "-m", "occflownet"]
    straight = tmp_path / "straight"
    subprocess.run([*cli, *_train_argv(root, straight, *common)], check=True, capture_output=True)

    killed = tmp_path / "killed"
    ckpt = killed / "checkpoints" / "last.pt"
    cmd = [*cli, *_train_argv(root, killed, *common)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not ckpt.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "training finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    step_at_kill = torch.load(ckpt, weights_only=True)["extra"]["train"]["step"]
    assert step_at_kill < MAX_STEPS
    subprocess.run([*cli, *_train_argv(root, killed, *common, "--resume")], check=True, capture_output=True)

    where = f"killed at step {step_at_kill}"
    assert_same_optimizer_steps(_train_state(straight / "checkpoints" / "last.pt"), _train_state(ckpt), where)
    tolerance = RESUME_TOLERANCE[supervision]
    losses = [{r["step"]: r["loss"] for r in map(json.loads, (run / "log.jsonl").read_text().splitlines())}
              for run in (straight, killed)]
    assert sorted(losses[1]) == sorted(losses[0]) == list(range(1, MAX_STEPS + 1))          # every step logged
    for step in range(step_at_kill + 1, MAX_STEPS + 1):   # every resumed step logged the straight run's loss
        assert losses[1][step] == pytest.approx(losses[0][step], rel=tolerance["loss_rtol"], abs=0), step
    raw_a, ema_a = _weights(straight / "checkpoints" / "last.pt")
    raw_b, ema_b = _weights(ckpt)
    for name in raw_a:      # the message keeps torch's (how far apart) and says where the run was killed
        said = lambda m, name=name: f"{name} ({where}): {m}"
        torch.testing.assert_close(raw_a[name], raw_b[name], rtol=0, atol=tolerance["atol"], msg=said)
        torch.testing.assert_close(ema_a[name], ema_b[name], rtol=0, atol=tolerance["atol"], msg=said)


def test_ddp_two_gloo_processes_hold_identical_weights(prepared_synth_root, tmp_path):
    root, _ = prepared_synth_root
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "occflownet",
           *_train_argv(root, out, "--max-steps", "3", "--horizon", "0", "--device", "cpu")]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    check = json.loads((out / "ddp_check.json").read_text())
    assert check["world_size"] == 2
    assert len(set(check["weights_sha256"])) == 1, check
    assert (out / "checkpoints" / "last.pt").is_file()


def test_3d_supervision_without_gts_fails_before_training(prepared_synth_root, tmp_path, capsys):
    import shutil

    root, _ = prepared_synth_root
    copy = tmp_path / "nogts"
    shutil.copytree(root, copy)
    shutil.rmtree(copy / "gts")
    assert main(["prepare", "--dataroot", str(copy), "--quiet"]) == 0
    rc = main(_train_argv(copy, tmp_path / "run3d", "--supervision", "3d", "--max-steps", "2"))
    assert rc != 0
    err = capsys.readouterr().err
    assert "Occ3D labels" in err and "gts" in err
    assert not (tmp_path / "run3d" / "checkpoints" / "last.pt").exists()


def test_free_space_beams_and_unmasked_voxel_losses_train(prepared_synth_root, tmp_path):
    # 2d+3d with free-space beams and beyond-grid rays: the log has the free-space term; the 3D losses run over
    # every voxel unless --voxel-mask is given (official use_mask=False)
    root, _ = prepared_synth_root
    out = tmp_path / "free"
    assert main(_train_argv(root, out, "--max-steps", "2", "--horizon", "1", "--supervision", "2d+3d",
                            "--free-space", "--free-beyond-grid", "--free-before-point", "--box-line-of-sight",
                            "--free-stretch", "points", "--free-rays-per-step", "256", "--head-init", "official",
                            "--free-ramp-steps", "0")) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert {"free_space", "free_before", "voxel_density", "render_depth"} <= set(log[0])
    assert log[0]["free_space"] > 0 and log[0]["free_before"] > 0
    assert log[0]["rays_per_s"] > 0 and log[0]["voxels_per_s"] > 0        # what the step supervised, per second
    config = json.loads((out / "train_config.json").read_text())
    assert config["free_space"] and config["free_beyond_grid"] and not config["voxel_mask"]
    assert config["free_before_point"] and config["box_line_of_sight"] and config["free_stretch"] == "points"
    assert config["head_init"] == "official"


def test_data_workers_with_the_free_stretch_walk_finish_and_load_what_the_main_process_loads(prepared_synth_root,
                                                                                               tmp_path):
    # Forked workers hung for ever here (the free stretches' parallel voxel walk with two numba threads, then a
    # torch op in collate): the loader now starts its workers. Same batches with and without workers.
    root, _ = prepared_synth_root
    recipe = ["--max-steps", "2", "--horizon", "0", "--no-flow", "--free-beyond-grid", "--free-before-point",
              "--free-stretch", "points", "--free-rays-per-step", "256"]
    env = dict(os.environ, OMP_NUM_THREADS="2", NUMBA_NUM_THREADS="2")
    workers = tmp_path / "workers"
    argv = _train_argv(root, workers, *recipe)
    argv[argv.index("--num-workers") + 1] = "2"
    res = subprocess.run([sys.executable, "-m", "occflownet", *argv], capture_output=True, text=True, timeout=150,
                         env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    inline = tmp_path / "inline"
    assert main(_train_argv(root, inline, *recipe)) == 0
    first = [json.loads((run / "log.jsonl").read_text().splitlines()[0]) for run in (workers, inline)]
    assert first[0]["step"] == first[1]["step"] == 1
    assert first[0]["loss"] == pytest.approx(first[1]["loss"], rel=1e-3)        # the same batch, the same init


def test_precision_autocasts_to_bf16_on_cuda_and_on_cpus_only_when_asked_and_native(monkeypatch):
    from occflownet.train.loop import autocast_dtype
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert autocast_dtype(cuda, "auto") == autocast_dtype(cuda, "bf16") == torch.bfloat16
    assert autocast_dtype(cuda, "fp32") is None
    for avx512_bf16, amx, native in ((False, False, False), (True, False, True), (False, True, True)):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda v=avx512_bf16: v)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda v=amx: v)
        assert autocast_dtype(cpu, "bf16") == (torch.bfloat16 if native else None)
        assert autocast_dtype(cpu, "auto") is None and autocast_dtype(cpu, "fp32") is None
    with pytest.raises(ValueError, match="precision"):
        autocast_dtype(cpu, "fp16")


def test_fp32_on_cuda_switches_tf32_off_and_nothing_else_touches_it():
    """cuDNN convolutions run in TF32 by default on CUDA: `--precision fp32` turns that (and TF32 matmuls) off, the
    other precisions and CPUs leave the flags as they are (set here, no GPU needed: they are process flags)."""
    from occflownet.train.loop import float32_math
    cudnn, matmul = torch.backends.cudnn, torch.backends.cuda.matmul
    saved = cudnn.allow_tf32, matmul.allow_tf32
    try:
        cudnn.allow_tf32 = matmul.allow_tf32 = True
        for device, precision in ((torch.device("cuda"), "auto"), (torch.device("cuda"), "bf16"),
                                  (torch.device("cpu"), "fp32")):
            float32_math(device, precision)
            assert cudnn.allow_tf32 and matmul.allow_tf32
        float32_math(torch.device("cuda"), "fp32")
        assert not cudnn.allow_tf32 and not matmul.allow_tf32
    finally:
        cudnn.allow_tf32, matmul.allow_tf32 = saved


def test_progress_bar_shows_what_the_run_processes_and_the_time_left_to_its_budget(tmp_path):
    from occflownet.train.distributed import DistInfo
    from occflownet.train.loop import _Monitor
    from occflownet.train.recipe import TrainConfig

    cfg = TrainConfig(supervision="3d", out=str(tmp_path), log_every=1, max_steps=10, time_limit_s=600)
    monitor = _Monitor(cfg, 0, DistInfo(), progress=True)
    monitor.after_step(1, {"loss": torch.tensor(2.5)}, torch.tensor(1.0), 1e-3, {"voxels": 640000})
    postfix = monitor.bar.postfix
    monitor.close()
    assert "loss=2.500" in postfix and "voxels_s=" in postfix and "rays_s" not in postfix
    minutes, seconds = postfix.split("budget_left=")[1].split(",")[0].split(":")
    assert 9 * 60 + 50 <= int(minutes) * 60 + int(seconds) <= 600
    assert (tmp_path / "log.jsonl").is_file()
