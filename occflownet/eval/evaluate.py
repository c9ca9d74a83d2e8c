"""The evaluation run behind `occflownet eval`: predict every sample of a split, accumulate Occ3D mIoU (with and
without the camera mask, per class, static/dynamic) and RayIoU (1, 2, 4 m), optionally save the predictions.

Two steps, so that bad data is reported before a model is loaded or anything runs:

1. :func:`select_samples` reads the index ``prepare`` wrote, picks the split and checks that every selected sample
   has its Occ3D labels (error naming the samples otherwise);
2. :func:`evaluate` runs a *predictor* over them and accumulates the metrics.

A predictor is an :class:`occflownet.runtime.Predictor` — ``OnnxPredictor.open(path)`` (onnxruntime, this path never
imports torch) or ``TorchPredictor(model_from_source(checkpoint))`` (a checkpoint's EMA weights in torch) — or any
callable on a batch of B samples::

    predict(ModelInputs: images uint8 [B, 6, H, W, 3] RGB in CAMERAS order,
                         intrinsics float32 [B, 6, 3, 3] (for that H × W),
                         cam2ego float32 [B, 6, 4, 4] camera (OpenCV) → current ego frame)
      → (occupancy uint8 [B, 200, 200, 16] [x, y, z], 17 = free, density float32 [B, 200, 200, 16])

i.e. the ONNX contract v1. Inputs are built as in training (``train/dataset.py``) by the one feeds function
(:func:`occflownet.runtime.frame_inputs`): images as stored, each camera's intrinsics, ``cam2ego`` =
``SampleRecord.cam2current_ego()`` (through each camera's own ego pose). Predictions and labels live in the current
ego frame of the keyframe (the ego pose at the LiDAR timestamp).
"""
from __future__ import annotations

import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from occflownet.contract import Calibration
from occflownet.occ3d import GRID
from occflownet.data.index import SampleIndex, load_index
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.tables import DatasetError
from occflownet.eval import OccupancyMetric, RayIoUMetric, scene_ray_origins
from occflownet.eval.fog import FogMetric, crossed_voxels
from occflownet.heap import reuse_freed_memory
from occflownet.options import check_fields, option
from occflownet.runtime import ModelInputs, Predictor, frame_inputs


# ----------------------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class EvalConfig:
    """What one evaluation covers and measures: the samples (:func:`select_samples`), the metrics and batches
    (:func:`evaluate`), what is written beside the result and the onnxruntime threads. `occflownet eval` derives
    its options from these fields (``occflownet/options.py``)."""

    version: str | None = option(None, "dataset version (default: the only one indexed)")
    split: str = option("val", "split to evaluate")
    max_samples: int | None = option(None, "evaluate only this many samples, the first of the split", minimum=1)
    batch_size: int = option(1, "samples per model call", minimum=1)
    rayiou: bool = option(True, "RayIoU (the slower metric, ~0.3 s per sample)")
    fog: bool = option(True, "the fog metric: predicted vs labelled occupied voxels in mask_camera, split by "
                             "whether a training ray of the frames within --fog-horizon crosses them; builds "
                             "those rays, ~1.5 s per sample")
    fog_horizon: int = option(3, "the fog metric's rays come from the frames t in [-FOG_HORIZON, FOG_HORIZON]",
                              minimum=0)
    save_predictions: str | None = option(None, "folder that receives <sample_token>.npz (occupancy uint8 "
                                                "[200,200,16], density float32) per sample")
    html: int | None = option(None, "with --save-predictions: also write <sample_token>.html there, the 3D viewer "
                                    "of the ground truth beside the prediction, for this many samples (the first)",
                              minimum=1)
    threads: int | None = option(None, "with --model: onnxruntime intra-op threads (default: all cores)", minimum=1)

    def __post_init__(self):
        check_fields(self)


# ----------------------------------------------------------------------------------------------- samples
@dataclass(frozen=True)
class EvalSamples:
    """The samples one evaluation runs over (all checked to have Occ3D labels)."""

    dataroot: Path
    index: SampleIndex
    split: str
    positions: np.ndarray    # int64 [N] positions in ``index``, scene order, time order within a scene

    def __len__(self) -> int:
        return len(self.positions)


def select_samples(dataroot, version: str | None = EvalConfig.version, split: str = EvalConfig.split,
                   max_samples: int | None = EvalConfig.max_samples) -> EvalSamples:
    """The samples of ``split`` (the first ``max_samples`` of them if given) of a prepared root.

    Errors (DatasetError / KeyError) name the problem: no index (run ``occflownet prepare``), an unknown split (lists
    the available ones), an empty selection, or samples without Occ3D labels (no ``gts/<scene>/`` directory when
    the index was written, or the labels file missing now) — evaluation needs every label, nothing is skipped."""
    dataroot = Path(dataroot)
    if max_samples is not None and max_samples < 1:
        raise ValueError(f"max_samples must be at least 1, got {max_samples}")
    index = load_index(dataroot, version)
    positions = index.split_positions(split)
    if max_samples is not None:
        positions = positions[:max_samples]
    if len(positions) == 0:
        raise DatasetError(f"split '{split}' of {dataroot} ({index.version}) has no samples")
    unlabeled, missing = [], []
    for p in positions:
        sample = index[int(p)]
        if sample.occupancy_path is None:
            unlabeled.append(f"{sample.token} ({sample.scene_name})")
        elif not (dataroot / sample.occupancy_path).is_file():
            missing.append(str(dataroot / sample.occupancy_path))
    problems = []
    if unlabeled:
        problems.append(f"{len(unlabeled)} have no Occ3D labels in the index (their scene had no gts/<scene>/ "
                        f"directory when `occflownet prepare` ran): {_first(unlabeled)}")
    if missing:
        problems.append(f"{len(missing)} have their Occ3D labels file missing: {_first(missing)}")
    if problems:
        raise DatasetError(f"cannot evaluate split '{split}' of {dataroot}: of {len(positions)} samples, "
                           + "; ".join(problems))
    return EvalSamples(dataroot, index, split, positions)


def _first(items: list[str], n: int = 5) -> str:
    return ", ".join(items[:n]) + (f", ... ({len(items) - n} more)" if len(items) > n else "")


# ----------------------------------------------------------------------------------------------- the run
@dataclass
class _Loaded:
    """Inputs and labels of consecutive samples whose images share one size."""

    positions: list
    tokens: list
    inputs: ModelInputs       # B frames: images uint8 [B, 6, H, W, 3], intrinsics [B, 6, 3, 3], cam2ego [B, 6, 4, 4]
    labels: list              # B Occupancy


def _load(samples: EvalSamples, positions) -> list[_Loaded]:
    """Load a batch; split it where the image size changes (a batch needs one H × W)."""
    records = [samples.index[int(p)] for p in positions]
    frames = [frame_inputs(load_sample_images(samples.dataroot, r),
                           Calibration.from_arrays(r.intrinsics, r.cam2current_ego())) for r in records]
    labels = [load_occupancy(samples.dataroot, r.occupancy_path) for r in records]
    groups, start = [], 0
    for i in range(1, len(records) + 1):
        if i == len(records) or frames[i].images.shape != frames[start].images.shape:
            part = slice(start, i)
            groups.append(_Loaded(positions=[int(p) for p in positions[part]],
                                  tokens=[r.token for r in records[part]],
                                  inputs=ModelInputs.stack(frames[part]), labels=labels[part]))
            start = i
    return groups


def _checked_outputs(out, batch: _Loaded) -> tuple[np.ndarray, np.ndarray]:
    """The predictor's (occupancy, density), checked against the contract; error naming the batch's samples."""
    b = len(batch.tokens)
    where = f"predictor output for samples {', '.join(batch.tokens)}"
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        raise ValueError(f"{where}: expected (occupancy, density), got {type(out).__name__}")
    occupancy, density = np.asarray(out[0]), np.asarray(out[1])
    want = (b, *GRID.shape)
    if occupancy.shape != want or density.shape != want:
        raise ValueError(f"{where}: expected occupancy and density of shape {want}, got {occupancy.shape} and "
                         f"{density.shape}")
    if not np.issubdtype(occupancy.dtype, np.integer):
        raise ValueError(f"{where}: occupancy must hold integer classes, got {occupancy.dtype}")
    return occupancy.astype(np.uint8, copy=False), density.astype(np.float32, copy=False)


def _fog_rays(samples: EvalSamples, fog_horizon: int | None):
    """The RayBuilder whose camera rays define the fog metric's 'crossed' voxels (training rays, t ∈ [-O, O]), or
    None when fog is off or the split has no lidarseg labels to build rays from."""
    from occflownet.data.rays import RayBuilder, RayConfig

    if fog_horizon is None or any(samples.index[int(p)].lidarseg_path is None for p in samples.positions):
        return None
    return RayBuilder(samples.index, samples.dataroot, RayConfig(horizon=fog_horizon), cache_size=2 * fog_horizon + 2)


class _Metrics:
    """The metrics of one run, updated per sample: Occ3D mIoU always, RayIoU and fog when asked."""

    def __init__(self, samples: EvalSamples, rayiou: bool, fog_horizon: int | None):
        self.samples = samples
        self.occupancy = OccupancyMetric()
        self.rayiou = RayIoUMetric() if rayiou else None
        self.fog_rays = _fog_rays(samples, fog_horizon)
        self.fog = FogMetric() if self.fog_rays is not None else None

    def update(self, position: int, token: str, occupancy: np.ndarray, gt) -> None:
        """One sample: ``occupancy`` uint8 [200, 200, 16] against its labels ``gt`` (an Occupancy); a ValueError
        names the sample."""
        try:
            self.occupancy.update(occupancy, gt.semantics, gt.mask_camera)
            if self.rayiou is not None:
                arrays = self.samples.index.arrays
                start, stop = self.samples.index.scene_range(position)
                origins = scene_ray_origins(arrays["lidar_sensor2ego"][start:stop],
                                            arrays["lidar_ego2global"][start:stop], position - start)
                self.rayiou.update(occupancy, gt.semantics, origins)
            if self.fog is not None:
                rays = self.fog_rays.rays(position)
                self.fog.update(occupancy, gt.semantics, gt.mask_camera,
                                crossed_voxels(rays.origins, rays.directions, rays.depths))
        except ValueError as exc:
            raise ValueError(f"sample {token}: {exc}") from exc

    def compute(self) -> dict:
        return {"occupancy": self.occupancy.compute(),
                "rayiou": self.rayiou.compute() if self.rayiou is not None else None,
                "fog": self.fog.compute() if self.fog is not None else None}


class _PredictionWriter:
    """Writes ``<token>.npz`` (occupancy uint8 [200, 200, 16], density float32 [200, 200, 16]) into a folder on a
    background thread; nothing when the folder is None. A failed write is raised at the next :meth:`check`."""

    def __init__(self, folder):
        self.folder = Path(folder) if folder is not None else None
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.pending = []

    def save(self, token: str, occupancy: np.ndarray, density: np.ndarray) -> None:
        if self.folder is not None:
            self.pending.append(self.pool.submit(np.savez_compressed, self.folder / f"{token}.npz",
                                                 occupancy=occupancy, density=density))

    def check(self, wait: bool = False) -> None:
        done = [f for f in self.pending if wait or f.done()]
        for f in done:
            f.result()
        self.pending = [f for f in self.pending if f not in done]

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None:
                self.check(wait=True)
        finally:
            self.pool.shutdown(wait=True)


def predictions(samples: EvalSamples, predict: Predictor, batch_size: int = EvalConfig.batch_size,
                timing: dict | None = None):
    """Yield ``(position, token, occupancy uint8 [200, 200, 16], density float32 [200, 200, 16], labels)`` for
    every sample, in order (``labels``: its Occupancy). Batches of ``batch_size`` (split where the image size
    changes); the next batch loads on a background thread while the model runs. ``timing``, if given, gains the
    seconds spent waiting for data (``"load"``) and in the model (``"predict"``)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    timing = {"load": 0.0, "predict": 0.0} if timing is None else timing
    batches = [samples.positions[i:i + batch_size] for i in range(0, len(samples), batch_size)]
    with ThreadPoolExecutor(max_workers=1) as loader:
        pending = loader.submit(_load, samples, batches[0])
        for b in range(len(batches)):
            t0 = time.perf_counter()
            groups = pending.result()
            timing["load"] += time.perf_counter() - t0     # time not hidden by the prefetch
            if b + 1 < len(batches):
                pending = loader.submit(_load, samples, batches[b + 1])
            for batch in groups:
                t0 = time.perf_counter()
                occupancy, density = _checked_outputs(predict(batch.inputs), batch)
                timing["predict"] += time.perf_counter() - t0
                yield from zip(batch.positions, batch.tokens, occupancy, density, batch.labels)


def evaluate(samples: EvalSamples, predict: Predictor, config: EvalConfig = EvalConfig(), *,
             progress: bool = True, **changes) -> dict:
    """Run ``predict`` over ``samples`` (batches of ``config.batch_size``) and return the JSON-ready result::

        {"dataroot", "version", "split", "samples", "batch_size",
         "occupancy": OccupancyMetric.compute() (camera_mask and all_voxels: miou, miou_static, miou_dynamic,
                      geometry_iou, iou_per_class, voxels, confusion),
         "rayiou": RayIoUMetric.compute() (rayiou, rayiou@1, rayiou@2, rayiou@4, iou_per_class, ...) or None,
         "fog": FogMetric.compute() (predicted vs labelled occupied voxels in mask_camera, split by whether a
                training ray of t ∈ [-fog_horizon, fog_horizon] crosses them) or None (``fog`` off, or
                the split has no lidarseg to build rays from),
         "timing": {"seconds", "load_seconds", "predict_seconds", "metric_seconds", "samples_per_second"}}

    Ray origins per sample: the LiDAR origins of its scene's keyframes moved into its current ego frame
    (``scene_ray_origins`` with the index's LiDAR sensor2ego and ego2global at the LiDAR timestamps).
    ``config.save_predictions``: a folder that receives ``<sample token>.npz`` with ``occupancy`` uint8
    [200, 200, 16] and ``density`` float32 [200, 200, 16]. Loading the next batch and writing predictions run on background
    threads while the model and the metrics work. Like ``train()``, it keeps freed memory in the process for reuse
    (:func:`occflownet.heap.reuse_freed_memory`: the torch model's large tensors stay mapped between samples).
    ``changes``: fields of :class:`EvalConfig` that replace those of ``config`` (``evaluate(s, p, rayiou=False)``);
    the fields that choose samples, viewers and threads are read by the caller."""
    from tqdm import tqdm

    config = replace(config, **changes)
    batch_size = config.batch_size
    reuse_freed_memory()
    metrics = _Metrics(samples, config.rayiou, config.fog_horizon if config.fog else None)
    timing = {"load": 0.0, "predict": 0.0, "metric": 0.0}
    t_start = time.perf_counter()
    with _PredictionWriter(config.save_predictions) as writer, \
            tqdm(total=len(samples), desc="eval", unit="sample", file=sys.stderr, disable=not progress) as bar:
        for position, token, occupancy, density, gt in predictions(samples, predict, batch_size, timing):
            writer.save(token, occupancy, density)
            t0 = time.perf_counter()
            metrics.update(position, token, occupancy, gt)
            timing["metric"] += time.perf_counter() - t0
            writer.check()                                    # a failed write stops the run now
            bar.update(1)
    seconds = time.perf_counter() - t_start
    return {
        "dataroot": str(samples.dataroot), "version": samples.index.version, "split": samples.split,
        "samples": len(samples), "batch_size": batch_size, **metrics.compute(),
        "timing": {"seconds": round(seconds, 3), "load_seconds": round(timing["load"], 3),
                   "predict_seconds": round(timing["predict"], 3), "metric_seconds": round(timing["metric"], 3),
                   "samples_per_second": round(len(samples) / seconds, 3) if seconds > 0 else None},
    }
