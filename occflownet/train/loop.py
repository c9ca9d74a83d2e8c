"""The training loop: AdamW + warm-up, grad-norm clipping, EMA, mixed precision, atomic checkpoints, exact resume,
DDP under torchrun, JSON-lines/TensorBoard logging, NaN guard, optional time limit.

Checkpoint layout (``<out>/checkpoints/last.pt``, plus ``step_<N>.pt`` copies are not kept): an occflownet model
checkpoint whose weights are the **EMA** weights (what ``eval`` and ``export`` use by default) and whose ``extra``
holds the training state: raw weights, optimizer, scheduler, EMA counters, step, RNG, the TrainConfig.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from occflownet.data.index import load_index
from occflownet.model import get_preset
from occflownet.model.checkpoint import read_checkpoint, save_checkpoint
from occflownet.model.occupancy_model import create_model
from occflownet.train import distributed as ddp
from occflownet.train.recipe import TrainConfig
from occflownet.train.dataset import TrainingSamples, collate
from occflownet.train.ema import EMA
from occflownet.train.run_log import RunLogger
from occflownet.train.sampler import StepBatchSampler
from occflownet.train.schedule import warmup_schedule
from occflownet.train.step import LossComputer


class TrainingError(RuntimeError):
    """Training cannot start or must stop; the message says why and what to do."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def last_checkpoint(out) -> Path:
    return Path(out) / "checkpoints" / "last.pt"


def _check_data(cfg: TrainConfig, index, positions) -> None:
    """Fail before training starts when the data cannot serve the requested supervision."""
    if len(positions) == 0:
        raise TrainingError(f"split '{cfg.split}' of {cfg.dataroot} has no samples")
    if cfg.uses_3d:
        missing = [index.tokens[p] for p in positions if index.arrays["occupancy_path"][p] in (b"", "")]
        if missing:
            raise TrainingError(
                f"--supervision {cfg.supervision} needs Occ3D labels, but {len(missing)} of {len(positions)} "
                f"samples have none under {Path(cfg.dataroot) / 'gts'} (first: {missing[0]}); "
                "use --supervision 2d or add the gts/ folder")
    if cfg.uses_2d and cfg.loss_weighting and index.class_stats is None:
        raise TrainingError(f"{cfg.dataroot}: the index has no class counts; run `occflownet prepare` again")


def _model_config(cfg: TrainConfig, index, positions):
    """The preset's ModelConfig with τ for this supervision and the training rig as default calibration."""
    model_cfg = get_preset(cfg.preset)
    sample = index[int(positions[0])]
    calib = {"cameras": {c.name: {"intrinsic": c.intrinsic.tolist(), "cam2ego": c.sensor2ego.tolist()}
                         for c in sample.cameras},
             "image_size": [int(sample.cameras[0].width), int(sample.cameras[0].height)]}
    head_init = cfg.head_init or model_cfg.head_init
    return replace(model_cfg, threshold=cfg.resolved_threshold(), default_calibration=calib, head_init=head_init)


def _load_flow(cfg: TrainConfig):
    if not cfg.flow:
        return None
    from occflownet.data.flow import flow_horizon, flow_path, load_flow_records

    path = flow_path(cfg.dataroot, cfg.version)
    covered = flow_horizon(cfg.dataroot, cfg.version)
    if not path.is_file() or covered is None:
        raise TrainingError(f"--flow needs precomputed box flows at {path}; run `occflownet prepare "
                            f"--dataroot {cfg.dataroot}` (it writes them)")
    if covered < cfg.horizon:
        raise TrainingError(f"{path} covers frames up to ±{covered}, training asks for --horizon {cfg.horizon}: "
                            f"run `occflownet prepare --dataroot {cfg.dataroot} --flow-horizon {cfg.horizon}`")
    return load_flow_records(path)


def _check_ranks_in_sync(model, info, out: Path) -> None:
    """Gather a hash of every rank's parameters; rank 0 records them in ``ddp_check.json`` and fails loudly if the
    replicas diverged (DDP keeps parameters identical; a mismatch means a broken set-up). BatchNorm running
    statistics are per rank after the last step (DDP broadcasts rank 0's at each forward); checkpoints hold
    rank 0's."""
    import hashlib

    import torch.distributed as dist

    digest = hashlib.sha256()
    for name, value in sorted(model.named_parameters()):
        digest.update(name.encode() + value.detach().cpu().contiguous().numpy().tobytes())
    hashes = [None] * info.world_size
    dist.all_gather_object(hashes, digest.hexdigest())
    if info.is_main:
        (out / "ddp_check.json").write_text(json.dumps({"world_size": info.world_size, "weights_sha256": hashes}))
        if len(set(hashes)) != 1:
            raise TrainingError(f"DDP replicas diverged: weight hashes per rank {hashes}")


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> Path:
    """Run (or resume) training; returns the path of the last checkpoint."""
    device = resolve_device(cfg.device)
    info = ddp.init_distributed(device)
    if device.type == "cuda":
        device = torch.device("cuda", info.local_rank)
        torch.cuda.set_device(device)
    out = Path(cfg.out)
    ckpt_path = last_checkpoint(out)

    index = load_index(cfg.dataroot, cfg.version)
    positions = index.split_positions(cfg.split)
    _check_data(cfg, index, positions)
    flow_records = _load_flow(cfg)

    model_cfg = _model_config(cfg, index, positions)
    model = create_model(model_cfg, seed=cfg.seed).to(device)
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        (no_decay if p.ndim <= 1 else decay).append(p)
    optimizer = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.weight_decay},
                                   {"params": no_decay, "weight_decay": 0.0}], lr=cfg.lr)
    scheduler = warmup_schedule(optimizer, cfg.warmup_steps)
    ema = EMA(model, cfg.ema_decay)
    start_step = 0

    if resume and ckpt_path.is_file():
        payload = read_checkpoint(ckpt_path)
        state = payload["extra"]["train"]
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        ema.shadow.load_state_dict(payload["state_dict"])
        ema.updates = int(state["ema_updates"])
        torch.set_rng_state(state["torch_rng"])
        start_step = int(state["step"])
        if info.is_main:
            print(f"resuming from {ckpt_path} at step {start_step}", file=sys.stderr)
    elif resume and info.is_main:
        print(f"--resume: no checkpoint at {ckpt_path}; starting from scratch", file=sys.stderr)

    if start_step >= cfg.max_steps:
        return ckpt_path

    weights = None
    if cfg.loss_weighting and index.class_stats is not None:
        weights = torch.as_tensor(np.asarray(index.class_stats.weights), dtype=torch.float32, device=device)
    losses = LossComputer(cfg, model_cfg, weights)

    net = model
    if info.enabled:
        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                      find_unused_parameters=not cfg.depth_loss)
    dataset = TrainingSamples(cfg.dataroot, index, positions, cfg, flow_records)
    sampler = StepBatchSampler(len(positions), cfg.batch_size, cfg.seed, start_step, cfg.max_steps,
                               info.rank, info.world_size)
    loader = DataLoader(dataset, batch_sampler=sampler, collate_fn=collate, num_workers=cfg.num_workers,
                        prefetch_factor=2 if cfg.num_workers > 0 else None)
    amp_dtype = torch.bfloat16 if device.type == "cuda" and cfg.amp else None
    logger = RunLogger(out, enabled=info.is_main)
    if info.is_main:
        out.mkdir(parents=True, exist_ok=True)
        (out / "train_config.json").write_text(json.dumps(cfg.to_dict(), indent=2))

    def save(step: int) -> None:
        if not info.is_main:
            return
        extra = {"train": {"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                           "scheduler": scheduler.state_dict(), "ema_updates": ema.updates, "step": step,
                           "torch_rng": torch.get_rng_state(), "config": cfg.to_dict()}}
        save_checkpoint(ckpt_path, ema.shadow, model_cfg, extra)

    bar = None
    if progress and info.is_main:
        from tqdm import tqdm

        bar = tqdm(total=cfg.max_steps, initial=start_step, desc="train", unit="step", file=sys.stderr,
                   dynamic_ncols=True)
    t_start = time.monotonic()
    t_log, rays_since_log = time.monotonic(), 0
    step = start_step
    model.train()
    for batch in loader:
        generator = torch.Generator(device=device).manual_seed(cfg.seed * 1_000_003 + step * 101 + info.rank)
        with torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None):
            outputs = net(batch["images"].to(device), batch["intrinsics"].to(device), batch["cam2ego"].to(device))
        terms = losses(outputs, batch, device, generator)
        loss = terms["loss"]
        if not torch.isfinite(loss):
            good = f"last good checkpoint: {ckpt_path}" if ckpt_path.is_file() else "no checkpoint was written yet"
            raise TrainingError(f"loss is {loss.item()} at step {step} ({ {k: float(v.detach()) for k, v in terms.items()} }); "
                                f"stopping; {good}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()
        scheduler.step()
        ema.update(model)
        step += 1
        rays_since_log += int(batch["ray_depths"].numel()) if "ray_depths" in batch else 0
        if info.is_main and (step % cfg.log_every == 0 or step == cfg.max_steps):
            now = time.monotonic()
            record = {k: float(v.detach()) for k, v in terms.items()}
            record.update(lr=scheduler.get_last_lr()[0], grad_norm=float(grad_norm),
                          rays_per_s=rays_since_log * info.world_size / max(now - t_log, 1e-9))
            logger.log(step, record)
            t_log, rays_since_log = now, 0
            if bar is not None:
                bar.set_postfix(loss=f"{record['loss']:.3f}", rays_s=f"{record['rays_per_s']:.0f}")
        if bar is not None:
            bar.update(1)
        out_of_time = cfg.time_limit_s > 0 and time.monotonic() - t_start > cfg.time_limit_s
        if info.enabled:  # every rank stops at the same step
            flag = torch.tensor([float(out_of_time)], device=device)
            out_of_time = bool(ddp.all_reduce_mean(flag, info).item() > 0)
        if step % cfg.checkpoint_every == 0 or step == cfg.max_steps or out_of_time:
            save(step)
        if out_of_time:
            if info.is_main:
                print(f"time limit of {cfg.time_limit_s:.0f} s reached at step {step}", file=sys.stderr)
            break
    if bar is not None:
        bar.close()
    logger.close()
    if info.enabled:
        _check_ranks_in_sync(model, info, out)
    ddp.barrier(info)
    ddp.shutdown(info)
    return ckpt_path
