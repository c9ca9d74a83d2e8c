"""The one predictor path: six camera images + their calibration → the model's inputs → a torch or ONNX model.

Every inference path (``occflownet predict``, ``eval``, export parity and variants, the server and its warm-up, the
benchmarks) goes through here, and nothing else builds model feeds or runs an onnxruntime session
(``tests/test_layout.py`` checks it):

- :func:`frame_inputs`: one frame's images + calibration → :class:`ModelInputs`. Its calibration half,
  :func:`frame_calibration` → :class:`FrameCalibration`, needs no pixels: the server calls it before it waits for a
  CPU slot (a bad calibration is answered at once) and fills in the decoded images after
  (:meth:`FrameCalibration.inputs`). The intrinsics are rescaled once, for the tensor the model gets, by the
  contract's pixel-centre rule (:meth:`occflownet.contract.Calibration.arrays_for`);
- :class:`ModelInputs`: a batch of contract-v1 inputs, cast and checked; :meth:`ModelInputs.feeds` is the
  onnxruntime feed dict;
- :class:`Predictor`: a model behind one batched interface, ``predictor(inputs) → (occupancy, density)``:
  :class:`OnnxPredictor` (an onnxruntime session, no torch) or :class:`TorchPredictor` (an ``OccupancyModel``).

Shipping wing (docs/layout.md): this module imports numpy and :mod:`occflownet.contract` only; onnxruntime when a
session is opened, torch only when a :class:`TorchPredictor` runs (it is handed a torch model: building one is the
training wing's, ``occflownet.model.model_from_source``).

Tensors (B frames, V = 6 cameras in ``CAMERAS`` order, H × W any image size):

- ``images`` uint8 [B, V, H, W, 3]: RGB as decoded (the graph crops and resizes inside);
- ``intrinsics`` float32 [B, V, 3, 3]: pinhole K in pixels for that H × W, integer coordinates at pixel centres;
- ``cam2ego`` float32 [B, V, 4, 4]: OpenCV camera frame (x right, y down, z forward) → ego frame of the keyframe
  (x forward, y left, z up), metres;
- ``occupancy`` uint8 [B, X, Y, Z]: [x, y, z] of the ego-frame grid, classes, ``free_index`` = free;
  ``density`` float32 [B, X, Y, Z]: σ ∈ [0, 1].
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import (CONTRACT_VERSION, INPUTS, OUTPUT_NAMES, Calibration, ModelMetadata, check_session,
                                 create_session, reduced_size, validate_calibration)
from occflownet.occ3d import CAMERAS

__all__ = ["FrameCalibration", "ModelInputs", "OnnxPredictor", "Predictor", "TorchPredictor", "frame_calibration",
           "frame_inputs"]


# ----------------------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class ModelInputs:
    """A batch of B frames as a contract-v1 model takes them: ``images`` uint8 [B, V, H, W, 3], ``intrinsics``
    float32 [B, V, 3, 3] (for H × W), ``cam2ego`` float32 [B, V, 4, 4] (camera → ego frame). Made C-contiguous in
    the contract's dtypes; ValueError naming the tensor on a wrong shape or when the batch sizes differ."""

    images: np.ndarray
    intrinsics: np.ndarray
    cam2ego: np.ndarray

    def __post_init__(self):
        for spec in INPUTS:
            a = np.ascontiguousarray(getattr(self, spec.name), dtype=spec.dtype)
            if a.ndim != spec.rank or any(w is not None and g != w for g, w in zip(a.shape, spec.shape)):
                raise ValueError(f"{spec.name}: shape {list(a.shape)} does not fit contract {CONTRACT_VERSION} "
                                 f"{list(spec.shape)}")
            object.__setattr__(self, spec.name, a)
        if len({len(self.images), len(self.intrinsics), len(self.cam2ego)}) != 1:
            raise ValueError(f"batch sizes differ: images {list(self.images.shape)}, intrinsics "
                             f"{list(self.intrinsics.shape)}, cam2ego {list(self.cam2ego.shape)}")

    @classmethod
    def frame(cls, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray) -> ModelInputs:
        """One frame (images [V, H, W, 3], intrinsics [V, 3, 3], cam2ego [V, 4, 4]) as a batch of one."""
        return cls(np.asarray(images)[None], np.asarray(intrinsics)[None], np.asarray(cam2ego)[None])

    @classmethod
    def stack(cls, parts: Sequence[ModelInputs]) -> ModelInputs:
        """The frames of ``parts`` (batches of one image size) as one batch, in order."""
        return cls(*(np.concatenate([getattr(p, s.name) for p in parts]) for s in INPUTS))

    def __len__(self) -> int:
        return len(self.images)

    @property
    def image_size(self) -> tuple[int, int]:
        """(w, h) of the images."""
        return int(self.images.shape[3]), int(self.images.shape[2])

    def split(self) -> list[ModelInputs]:
        """Each frame as a batch of one (views, no copy)."""
        return [ModelInputs(self.images[b:b + 1], self.intrinsics[b:b + 1], self.cam2ego[b:b + 1])
                for b in range(len(self))]

    def feeds(self) -> dict[str, np.ndarray]:
        """The onnxruntime feed dict {input name: array} (the only one the code base builds)."""
        return {spec.name: getattr(self, spec.name) for spec in INPUTS}


@dataclass(frozen=True)
class FrameCalibration:
    """One frame's calibration as the model takes it, before any pixel is decoded: the (w, h) of the image tensor,
    ``intrinsics`` float32 [V, 3, 3] for images of that size, ``cam2ego`` float32 [V, 4, 4] (camera → ego)."""

    size: tuple[int, int]
    intrinsics: np.ndarray
    cam2ego: np.ndarray

    @property
    def image_shape(self) -> tuple[int, int, int, int]:
        """(V, h, w, 3): the shape of the frame's image tensor."""
        w, h = self.size
        return len(self.intrinsics), h, w, 3

    def inputs(self, images: np.ndarray) -> ModelInputs:
        """images uint8 [V, h, w, 3] (RGB, camera order) of this frame → its ModelInputs, a batch of one."""
        if tuple(np.shape(images)) != self.image_shape:
            raise ValueError(f"images {list(np.shape(images))} do not have the frame's shape {list(self.image_shape)}")
        return ModelInputs.frame(images, self.intrinsics, self.cam2ego)


def frame_calibration(calibration: Mapping | Calibration, sizes: Sequence[tuple[int, int]], *,
                      reductions: Sequence[int] | None = None, size: tuple[int, int] | None = None,
                      cameras: Sequence[str] = CAMERAS, source: str = "the calibration",
                      remedy: str = "a calibration") -> FrameCalibration:
    """The calibration half of :func:`frame_inputs`, for callers that check it before they decode the images.

    ``calibration``: calibration JSON (validated here: CalibrationError naming the camera and the field) or a
    :class:`~occflownet.contract.Calibration`. ``sizes``: per camera (in ``cameras`` order) the (w, h) of its image
    as stored. ``reductions``: per camera the n its JPEG is decoded at 1/n (the reduced-scale rule; default 1).
    ``size``: the (w, h) every decoded image is resized to (the server's common size); default the decoded size,
    which must then be the same for every camera. The intrinsics go from the calibration's size to ``size`` in one
    rescale (:meth:`Calibration.arrays_for`; ``source`` and ``remedy`` word its aspect-ratio error)."""
    cal = calibration if isinstance(calibration, Calibration) else validate_calibration(calibration, cameras)
    if reductions is None:
        reductions = [1] * len(sizes)
    if size is None:
        decoded = {reduced_size(int(w), int(h), n) for (w, h), n in zip(sizes, reductions)}
        if len(decoded) != 1:
            raise ValueError(f"images decode to different sizes {sorted(decoded)}: give the size to resize them to")
        size = decoded.pop()
    K, T = cal.arrays_for(sizes, source, remedy, reductions=reductions, size=size)
    return FrameCalibration((int(size[0]), int(size[1])), K, T)


def frame_inputs(images: np.ndarray, calibration: Mapping | Calibration, *,
                 sizes: Sequence[tuple[int, int]] | None = None, reductions: Sequence[int] | None = None,
                 cameras: Sequence[str] = CAMERAS, source: str = "the calibration",
                 remedy: str = "a calibration") -> ModelInputs:
    """Images + calibration → model inputs, for one frame: the function every inference path feeds a model with.

    ``images``: uint8 [V, h, w, 3] RGB in ``cameras`` order, all at one size (w, h), as decoded (and resized).
    ``calibration``: calibration JSON or a :class:`~occflownet.contract.Calibration` (a dataset's arrays:
    ``Calibration.from_arrays``). ``sizes``: per camera the (w, h) of its stored image (default: (w, h), the
    images are as stored); ``reductions``: the 1/n each JPEG was decoded at (default 1). Returns ModelInputs of a
    batch of one with the intrinsics for (w, h) (see :func:`frame_calibration`)."""
    h, w = np.shape(images)[1:3]
    sizes = [(w, h)] * len(cameras) if sizes is None else sizes
    return frame_calibration(calibration, sizes, reductions=reductions, size=(w, h), cameras=cameras,
                             source=source, remedy=remedy).inputs(images)


# ----------------------------------------------------------------------------------------------- predictors
class Predictor:
    """A contract-v1 model behind one batched interface: ``predictor(inputs)`` with B frames of
    :class:`ModelInputs` → (occupancy uint8 [B, X, Y, Z], density float32 [B, X, Y, Z]); ``predict(inputs,
    outputs)`` returns the named outputs only, in that order. ``input_size`` is the [H, W] the network resizes
    every image to (what the reduced-scale JPEG rule needs), None when unknown."""

    input_size: tuple[int, int] | None = None

    def predict(self, inputs: ModelInputs, outputs: Sequence[str] = OUTPUT_NAMES) -> tuple[np.ndarray, ...]:
        raise NotImplementedError

    def __call__(self, inputs: ModelInputs) -> tuple[np.ndarray, np.ndarray]:
        occupancy, density = self.predict(inputs)
        return occupancy, density


class OnnxPredictor(Predictor):
    """An exported model run by onnxruntime (never torch). ``session``: an onnxruntime session (or anything with
    its ``run(output names, feeds)``); ``metadata``: its contract-v1 metadata when checked."""

    def __init__(self, session, metadata: ModelMetadata | None = None):
        self.session = session
        self.metadata = metadata
        self.input_size = metadata.input_size if metadata is not None else None

    @classmethod
    def open(cls, path: str | Path, threads: int | None = None, *, spinning: bool = False,
             providers: list[str] | None = None) -> OnnxPredictor:
        """The model file ``path`` in a session of :func:`occflownet.contract.create_session` (``threads`` intra-op
        threads, default all cores), checked against contract v1. FileNotFoundError, ValueError or ContractError
        naming the file."""
        session = create_session(path, threads, spinning=spinning, providers=providers, check_contract=False)
        return cls(session, check_session(session, str(path)))

    def predict(self, inputs: ModelInputs, outputs: Sequence[str] = OUTPUT_NAMES) -> tuple[np.ndarray, ...]:
        return tuple(self.session.run(list(outputs), inputs.feeds()))


class TorchPredictor(Predictor):
    """An ``OccupancyModel`` (or anything with its ``inference(images, intrinsics, cam2ego)`` and ``cfg``) run in
    torch without gradients, put in eval mode (torch is imported when it runs, not with this module)."""

    def __init__(self, model):
        self.model = model.eval()
        self.input_size = tuple(int(v) for v in model.cfg.input_size)

    def predict(self, inputs: ModelInputs, outputs: Sequence[str] = OUTPUT_NAMES) -> tuple[np.ndarray, ...]:
        import torch

        with torch.inference_mode():
            occupancy, density = self.model.inference(torch.from_numpy(inputs.images),
                                                      torch.from_numpy(inputs.intrinsics),
                                                      torch.from_numpy(inputs.cam2ego))
        found = {"occupancy": occupancy.numpy(), "density": density.numpy()}
        return tuple(found[name] for name in outputs)
