"""The evaluation run behind `occflownet eval`: predict every sample of a split, accumulate Occ3D mIoU (with and
without the camera mask, per class, static/dynamic) and RayIoU (1, 2, 4 m), optionally save the predictions.

A *predictor* is any callable ``(images uint8 [6, H, W, 3], intrinsics float32 [6, 3, 3], cam2ego float32
[6, 4, 4]) → (occupancy uint8 [200, 200, 16], density float32 [200, 200, 16])``: the torch model of a checkpoint
(:func:`checkpoint_predictor`) or the exported ONNX graph (:func:`onnx_predictor`, onnxruntime only, no torch).
Inputs follow training: images as stored, each camera's intrinsics, and ``cam2ego`` = camera → current ego frame
(through each camera's own ego pose). Predictions and labels are in the current ego frame of the keyframe.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import numpy as np

from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.tables import DatasetError
from occflownet.eval import OccupancyMetric, RayIoUMetric, scene_ray_origins

Predictor = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple]


def checkpoint_predictor(path) -> Predictor:
    """The (EMA) weights of an occflownet checkpoint, run in torch."""
    import torch

    from occflownet.model.checkpoint import load_checkpoint

    model, _, _ = load_checkpoint(path)
    model.eval()

    def predict(images, intrinsics, cam2ego):
        with torch.inference_mode():
            occ, dens = model.inference(torch.from_numpy(images)[None], torch.from_numpy(intrinsics)[None],
                                        torch.from_numpy(cam2ego)[None])
        return occ[0].numpy(), dens[0].numpy()

    return predict


def onnx_predictor(path) -> Predictor:
    """An exported model run by onnxruntime (no torch import on this path)."""
    from occflownet.inference_io import create_session, run_session

    session = create_session(path)
    return lambda images, intrinsics, cam2ego: run_session(session, images, intrinsics, cam2ego)


def evaluate(dataroot, predict: Predictor, version: str | None = None, split: str = "val",
             save_predictions=None, max_samples: int | None = None, rayiou: bool = True,
             progress: bool = True) -> dict:
    """Evaluate ``predict`` on ``split`` of a prepared root; returns the JSON-ready result dict."""
    from tqdm import tqdm

    dataroot = Path(dataroot)
    index = load_index(dataroot, version)
    positions = index.split_positions(split)
    if max_samples is not None:
        positions = positions[:max_samples]
    if len(positions) == 0:
        raise DatasetError(f"split '{split}' of {dataroot} has no samples")
    missing = [index.tokens[p] for p in positions if index[int(p)].occupancy_path is None]
    if missing:
        raise DatasetError(f"{len(missing)} samples of split '{split}' have no Occ3D labels under "
                           f"{dataroot / 'gts'} (first: {missing[0]}): evaluation needs them")
    out_dir = Path(save_predictions) if save_predictions else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    occ_metric, ray_metric = OccupancyMetric(), RayIoUMetric() if rayiou else None
    a = index.arrays
    for p in tqdm(positions, desc="eval", unit="sample", file=sys.stderr, disable=not progress):
        sample = index[int(p)]
        images = load_sample_images(dataroot, sample)
        occupancy, density = predict(images, sample.intrinsics.astype(np.float32),
                                     sample.cam2current_ego().astype(np.float32))
        gt = load_occupancy(dataroot, sample.occupancy_path)
        occ_metric.update(occupancy, gt.semantics, gt.mask_camera)
        if ray_metric is not None:
            start, stop = index.scene_range(int(p))
            origins = scene_ray_origins(a["lidar_sensor2ego"][start:stop], a["lidar_ego2global"][start:stop],
                                        int(p) - start)
            ray_metric.update(occupancy, gt.semantics, origins)
        if out_dir is not None:
            np.savez_compressed(out_dir / f"{sample.token}.npz", occupancy=np.asarray(occupancy, np.uint8),
                                density=np.asarray(density, np.float32))
    return {"dataroot": str(dataroot), "version": index.version, "split": split, "samples": int(len(positions)),
            "occupancy": occ_metric.compute(), "rayiou": ray_metric.compute() if ray_metric is not None else None}
