"""The training loop: set-up, the optimisation step (AdamW + warm-up, grad-norm clipping, EMA, mixed precision),
logging, the stop conditions (NaN guard, max steps, optional time limit), DDP under torchrun.

The state the loop carries (model, EMA, optimiser, schedule, step) is a :class:`~occflownet.train.state.TrainingState`;
``<out>/checkpoints/last.pt`` is its ``save`` (the layout is in ``occflownet/train/state.py``) and ``--resume`` its
``load``. Data order and ray sampling are pure functions of (seed, step), so a resumed run continues the same
run, up to float rounding (docs/training.md, "Checkpoints, resume, failures").
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from occflownet.choices import PRECISIONS
from occflownet.contract import calibration_json
from occflownet.data.index import load_index
from occflownet.files import atomic_path
from occflownet.heap import reuse_freed_memory
from occflownet.model import get_preset
from occflownet.model.presets import ModelConfig
from occflownet.train import distributed as ddp
from occflownet.train.dataset import TrainingSamples, collate
from occflownet.train.losses import loss_terms, step_data
from occflownet.train.recipe import TrainConfig
from occflownet.train.run_log import RunLogger
from occflownet.train.sampler import StepBatchSampler
from occflownet.train.state import TrainingError, TrainingState
from occflownet.train.step import LossComputer
from occflownet.worker_processes import spawn_context


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> Path:
    """Run training, or with ``resume`` continue it from ``<out>/checkpoints/last.pt`` (from scratch when there is
    none yet); returns the path of the last checkpoint. Under torchrun every rank calls it; rank 0 logs and saves.
    It keeps freed memory in the process for reuse (:func:`occflownet.heap.reuse_freed_memory`), for the rest of
    the process's life."""
    reuse_freed_memory()                                     # a step's large tensors stay mapped between steps
    device, info = _init_device(cfg)
    ckpt_path = last_checkpoint(cfg.out)
    index, positions, flow_records = _training_data(cfg)
    state = _initial_state(cfg, _model_config(cfg, index, positions), device, ckpt_path, resume, info)
    if state.step >= cfg.max_steps:                          # nothing left to do: leave the process group
        ddp.barrier(info)
        ddp.shutdown(info)
        return ckpt_path
    losses = LossComputer(cfg, state.model_cfg, _class_weights(cfg, index, device))
    loader = _data_loader(cfg, index, positions, flow_records, state.step, info)
    _write_train_config(cfg, info)
    monitor = _Monitor(cfg, state.step, info, progress)
    _run_steps(state, _distributed(state.model, cfg, info, device), losses, loader, monitor, ckpt_path, device, info)
    monitor.close()
    _finish(state.model, info, Path(cfg.out))
    return ckpt_path


# --- set-up -----------------------------------------------------------------------------------------------------------

def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def autocast_dtype(device: torch.device, precision: str = "auto") -> torch.dtype | None:
    """The network's autocast dtype for ``--precision`` (:data:`~occflownet.choices.PRECISIONS`): bfloat16 on CUDA
    unless ``fp32``; on a CPU only for ``bf16`` and only where it computes bf16 natively (AVX512-BF16 or AMX: emulated
    bf16 is slower than float32); None (float32) otherwise. ``auto`` keeps CPUs in float32 because bf16 autocast
    there, 1.4x faster a step, spiked the loss in long runs that float32 fitted (docs/results.md#training-speed)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "fp32":
        return None
    if device.type == "cuda":
        return torch.bfloat16
    native = device.type == "cpu" and (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    return torch.bfloat16 if precision == "bf16" and native else None


def float32_math(device: torch.device, precision: str) -> None:
    """Make ``--precision fp32`` float32 on CUDA too: PyTorch runs cuDNN convolutions in TF32 (a 10-bit mantissa)
    unless told otherwise, so without this the decoder's 3D convolutions of an "fp32" run on a GPU would not be
    float32. Switches TF32 off for cuDNN and CUDA matmuls in this process for ``fp32`` on CUDA; leaves them alone
    otherwise (bf16 autocast and CPUs do not read them)."""
    if device.type == "cuda" and precision == "fp32":
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_tf32 = False


def last_checkpoint(out) -> Path:
    return Path(out) / "checkpoints" / "last.pt"


def _init_device(cfg: TrainConfig) -> tuple[torch.device, ddp.DistInfo]:
    """The training device and this process's place in the torchrun group (rank 0 of 1 without torchrun)."""
    device = resolve_device(cfg.device)
    info = ddp.init_distributed(device)
    if device.type == "cuda":
        device = torch.device("cuda", info.local_rank)
        torch.cuda.set_device(device)
    return device, info


def _training_data(cfg: TrainConfig):
    """→ (SampleIndex, int64 [S] positions of the split's samples, flow records or None), checked for ``cfg``."""
    index = load_index(cfg.dataroot, cfg.version)
    positions = index.split_positions(cfg.split)
    _check_data(cfg, index, positions)
    return index, positions, _load_flow(cfg)


def _check_data(cfg: TrainConfig, index, positions) -> None:
    """Fail before training starts when the data cannot serve what the run's loss terms read
    (``losses.INPUT_DATA``)."""
    if len(positions) == 0:
        raise TrainingError(f"split '{cfg.split}' of {cfg.dataroot} has no samples")
    data = step_data(loss_terms(cfg))
    if "voxel_labels" in data:
        missing = [index.tokens[p] for p in positions if index.arrays["occupancy_path"][p] in (b"", "")]
        if missing:
            raise TrainingError(
                f"recipe {cfg.recipe!r} (--supervision {cfg.supervision}) needs Occ3D labels, but {len(missing)} of "
                f"{len(positions)} samples have none under {Path(cfg.dataroot) / 'gts'} (first: {missing[0]}); "
                "choose a recipe without 3D labels (`occflownet recipes`) or add the gts/ folder")
    if "class_counts" in data and index.class_stats is None:
        raise TrainingError(f"{cfg.dataroot}: the index has no class counts; run `occflownet prepare` again")


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


def _model_config(cfg: TrainConfig, index, positions):
    """The preset's ModelConfig with τ for this supervision, the training rig as default calibration and the image
    head when a loss term trains it."""
    model_cfg = get_preset(cfg.preset)
    sample = index[int(positions[0])]
    calib = calibration_json(sample.intrinsics, sample.cam2ego, sample.image_sizes[0])
    head_init = cfg.head_init or model_cfg.head_init
    return replace(model_cfg, threshold=cfg.resolved_threshold(), default_calibration=calib, head_init=head_init,
                   image_semantics=cfg.image_semantics_weight > 0)


def _initial_state(cfg: TrainConfig, model_cfg: ModelConfig, device, ckpt_path: Path, resume: bool,
                   info) -> TrainingState:
    """With ``resume`` and a checkpoint at ``ckpt_path``: the state saved there, continued under ``cfg``;
    otherwise a fresh state of ``model_cfg``."""
    if resume and ckpt_path.is_file():
        state = TrainingState.load(ckpt_path, device, cfg)
        if info.is_main:
            print(f"resuming from {ckpt_path} at step {state.step}", file=sys.stderr)
        return state
    if resume and info.is_main:
        print(f"--resume: no checkpoint at {ckpt_path}; starting from scratch", file=sys.stderr)
    return TrainingState.create(cfg, model_cfg, device)


def _class_weights(cfg: TrainConfig, index, device) -> torch.Tensor | None:
    """float32 [17] ray weights ω(label) from `prepare`'s class counts, or None (uniform)."""
    if not cfg.loss_weighting or index.class_stats is None:
        return None
    return torch.as_tensor(np.asarray(index.class_stats.weights), dtype=torch.float32, device=device)


def _distributed(model: torch.nn.Module, cfg: TrainConfig, info, device) -> torch.nn.Module:
    """``model`` wrapped in DDP under torchrun, else ``model`` itself (what the forward pass calls)."""
    if not info.enabled:
        return model
    return DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                   find_unused_parameters=not cfg.depth_loss)


def _data_loader(cfg: TrainConfig, index, positions, flow_records, start_step: int, info) -> DataLoader:
    """Batches (:func:`collate`) of this rank's samples for steps ``start_step .. max_steps-1``."""
    dataset = TrainingSamples(cfg.dataroot, index, positions, cfg, flow_records)
    sampler = StepBatchSampler(len(positions), cfg.batch_size, cfg.seed, start_step, cfg.max_steps,
                               info.rank, info.world_size)
    # Workers are started, not forked: a fork of this process inherits an OpenMP runtime (torch's, numba's threading
    # layer) that already ran parallel regions, and with more than one thread its first parallel region in the
    # worker can wait forever (seen with --free-stretch points at NUMBA_NUM_THREADS=2: every worker idle in
    # collate's torch.stack). A started worker imports its own runtime, at a cost of seconds once per run.
    return DataLoader(dataset, batch_sampler=sampler, collate_fn=collate, num_workers=cfg.num_workers,
                      prefetch_factor=2 if cfg.num_workers > 0 else None,
                      multiprocessing_context=spawn_context() if cfg.num_workers > 0 else None)


def _write_train_config(cfg: TrainConfig, info) -> None:
    """``<out>/train_config.json``: the resolved TrainConfig of this run (rank 0)."""
    if info.is_main:
        with atomic_path(Path(cfg.out) / "train_config.json") as tmp:
            tmp.write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")


# --- the steps --------------------------------------------------------------------------------------------------------

def _run_steps(state: TrainingState, net, losses: LossComputer, loader: Iterable[dict], monitor: "_Monitor",
               ckpt_path: Path, device, info) -> None:
    """Optimisation steps until the loader ends (at ``max_steps``) or the time limit; rank 0 saves ``state`` to
    ``ckpt_path`` every ``checkpoint_every`` steps, at the last step and at the time limit."""
    cfg = state.cfg
    amp_dtype = autocast_dtype(device, cfg.precision)
    float32_math(device, cfg.precision)
    if cfg.precision == "bf16" and amp_dtype is None and info.is_main:
        print("--precision bf16: this CPU has no native bf16 (AVX512-BF16 or AMX); training in float32",
              file=sys.stderr)
    t_start = time.monotonic()
    state.model.train()
    for batch in loader:
        generator = torch.Generator(device=device).manual_seed(cfg.seed * 1_000_003 + state.step * 101 + info.rank)
        terms, grad_norm = train_step(state, net, losses, batch, device, generator, amp_dtype)
        monitor.after_step(state.step, terms, grad_norm, state.scheduler.get_last_lr()[0], step_work(batch))
        out_of_time = _out_of_time(cfg, t_start, info, device)
        if info.is_main and (_checkpoint_due(cfg, state.step) or out_of_time):
            state.save(ckpt_path)
        if out_of_time:
            if info.is_main:
                print(f"time limit of {cfg.time_limit_s:.0f} s reached at step {state.step}", file=sys.stderr)
            return


def train_step(state: TrainingState, net, losses: LossComputer, batch: dict, device, generator: torch.Generator,
               amp_dtype: torch.dtype | None = None) -> tuple[dict, torch.Tensor]:
    """One optimisation step; ``state.step`` += 1.

    ``batch``: from :func:`collate` (images uint8 [B, 6, H, W, 3], intrinsics [B, 6, 3, 3], cam2ego [B, 6, 4, 4]
    camera → current ego, rays and labels in the current ego frame). ``net``: ``state.model`` or its DDP wrapper; its
    heads run on the voxels the losses read only when no term needs the whole grid (``LossComputer.head_rows``).
    ``generator``: the render jitter of this step. Forward under autocast(``amp_dtype``) when given, losses (a
    non-finite loss raises TrainingError), backward, grad-norm clip, AdamW and schedule step, EMA update.
    → (loss terms {name: scalar tensor, "loss": total}, grad norm before clipping)."""
    with torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None):
        outputs = net(batch["images"].to(device), batch["intrinsics"].to(device), batch["cam2ego"].to(device),
                      **losses.head_rows(batch, device))
    terms = losses(outputs, batch, device, generator, step=state.step)
    _stop_if_not_finite(terms, state.step, last_checkpoint(state.cfg.out))
    state.optimizer.zero_grad(set_to_none=True)
    terms["loss"].backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(state.model.parameters(), state.cfg.grad_clip)
    state.optimizer.step()
    state.scheduler.step()
    state.ema.update(state.model)
    state.step += 1
    return terms, grad_norm


def step_work(batch: dict) -> dict[str, int]:
    """What one step of this process supervises, by what its batch carries: {"rays": LiDAR rays rendered} when it
    carries rays, {"voxels": labelled voxels in the 3D loss (inside mask_camera with ``voxel_mask``)} when it
    carries voxel labels."""
    work = {}
    if "ray_depths" in batch:
        work["rays"] = int(batch["ray_depths"].numel())
    if "voxel_occupied" in batch:
        work["voxels"] = int(batch["voxel_occupied"].numel())
    return work


# --- stop conditions and the end --------------------------------------------------------------------------------------

def _stop_if_not_finite(terms: dict, step: int, ckpt_path: Path) -> None:
    """TrainingError naming the step, the loss terms and the last good checkpoint when the total loss is not finite."""
    loss = terms["loss"]
    if torch.isfinite(loss):
        return
    good = f"last good checkpoint: {ckpt_path}" if ckpt_path.is_file() else "no checkpoint was written yet"
    values = {k: float(v.detach()) for k, v in terms.items()}
    raise TrainingError(f"loss is {loss.item()} at step {step} ({values}); stopping; {good}")


def _out_of_time(cfg: TrainConfig, t_start: float, info, device) -> bool:
    """Whether ``cfg.time_limit_s`` (0 = none) has passed since ``t_start``; under DDP every rank gets the same answer
    (any rank out of time stops all at the same step)."""
    out_of_time = cfg.time_limit_s > 0 and time.monotonic() - t_start > cfg.time_limit_s
    if info.enabled:
        flag = torch.tensor([float(out_of_time)], device=device)
        out_of_time = bool(ddp.all_reduce_mean(flag, info).item() > 0)
    return out_of_time


def _checkpoint_due(cfg: TrainConfig, step: int) -> bool:
    return step % cfg.checkpoint_every == 0 or step == cfg.max_steps


def _finish(model: torch.nn.Module, info, out: Path) -> None:
    """Under DDP: check that the replicas hold the same weights, then leave the process group."""
    if info.enabled:
        _check_ranks_in_sync(model, info, out)
    ddp.barrier(info)
    ddp.shutdown(info)


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


# --- logging ----------------------------------------------------------------------------------------------------------

class _Monitor:
    """Rank 0's record of the run: ``log.jsonl`` (and TensorBoard) every ``log_every`` steps and at the last step,
    the tqdm bar on stderr when ``progress``."""

    def __init__(self, cfg: TrainConfig, start_step: int, info, progress: bool):
        self.cfg, self.world_size = cfg, info.world_size
        self.logger = RunLogger(Path(cfg.out), enabled=info.is_main)
        self.bar = None
        if progress and info.is_main:
            from tqdm import tqdm

            self.bar = tqdm(total=cfg.max_steps, initial=start_step, desc="train", unit="step", file=sys.stderr,
                            dynamic_ncols=True)
        self.t_start = self.t_log = time.monotonic()
        self.work_since_log = {}

    def after_step(self, step: int, terms: dict, grad_norm: torch.Tensor, lr: float, work: dict[str, int]) -> None:
        """Record step ``step`` (counted after the update): loss terms, lr, grad norm, and per second over all ranks
        what the steps supervised (``work``, :func:`step_work`: ``rays_per_s`` and/or ``voxels_per_s``); the bar
        shows the loss, those rates and, under ``time_limit_s``, the time left to that budget (tqdm adds steps/s and
        the time to ``max_steps``; the run ends at whichever comes first)."""
        for key, n in work.items():
            self.work_since_log[key] = self.work_since_log.get(key, 0) + n
        if self.logger.enabled and (step % self.cfg.log_every == 0 or step == self.cfg.max_steps):
            now = time.monotonic()
            rates = {f"{key}_per_s": n * self.world_size / max(now - self.t_log, 1e-9)
                     for key, n in self.work_since_log.items()}
            record = {k: float(v.detach()) for k, v in terms.items()}
            record.update(lr=lr, grad_norm=float(grad_norm), **rates)
            self.logger.log(step, record)
            self.t_log, self.work_since_log = now, {}
            if self.bar is not None:
                postfix = {"loss": f"{record['loss']:.3f}",
                           **{key.replace("_per_s", "_s"): f"{v:.0f}" for key, v in rates.items()}}
                if self.cfg.time_limit_s > 0:
                    left = max(0.0, self.cfg.time_limit_s - (now - self.t_start))
                    postfix["budget_left"] = f"{int(left // 60)}:{int(left % 60):02d}"
                self.bar.set_postfix(postfix)
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.logger.close()
