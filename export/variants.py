"""Reduced-precision variants of an exported fp32 graph, each reported against the fp32 model.

- fp16: weights and activations in float16 (``onnxruntime.transformers.float16``); inputs/outputs keep their
  contract-v1 types, and the geometry/pooling/threshold ops stay in float32 (their indices must be exact).
- int8: static QDQ quantisation (``onnxruntime.quantization.quantize_static``) of the image convolutions only
  (:data:`INT8_OP_TYPES`; the 3D decoder's convolutions after the voxel pooling stay float32, :func:`voxel_convs`),
  per-channel int8 weights with 7-bit range (``int8_range="reduced"``, or 8-bit), uint8 activations calibrated
  (MinMax) on real-looking frames (:class:`_CalibrationReader`: the ``frame`` folder as the inference paths decode
  it — JPEGs at reduced scale — with photometric variations and turned rigs, else synthetic samples). The
  per-voxel layers (Gemm: the depth-to-space projection and the heads Φσ, Φs) and the
  image resampling MatMuls stay float32: σ ≥ τ and the argmax are decided there, and they are memory-bound
  (int8 would add quantise/dequantise passes over 640,000-row tensors and gain nothing).

Agreement with fp32 on the evaluation sample (the real frame when given, else a random one): fraction of equal
occupancy voxels and density max abs diff. A variant that onnxruntime cannot load or that is not standard ONNX
raises; agreement is reported, not enforced (reduced precision is expected to differ).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import onnx

from occflownet.choices import INT8_RANGES
from occflownet.export.config import ExportConfig
from occflownet.export.onnx_export import ExportError, agreement, validate_proto
from occflownet.export.parity import default_parity_samples, inference_frame_sample
from occflownet.model import ModelConfig
from occflownet.occ3d import FREE
from occflownet.runtime import ModelInputs, OnnxPredictor

# ops kept in float32 in the fp16 variant: index/geometry arithmetic, pooling, resize, fusion
FP16_KEEP_FP32 = ["Resize", "ScatterND", "ScatterElements", "Floor", "Where", "Range", "NonZero", "GatherND",
                  "ArgMax", "Sigmoid", "Softmax", "Div", "Reciprocal", "Min", "Max", "CumSum", "Clip",
                  "GreaterOrEqual", "Less", "LessOrEqual", "Greater", "Equal", "Cast", "IsNaN", "IsInf", "Expand",
                  "Concat", "Slice"]


def _with_suffix(path: Path, tag: str) -> Path:
    return path.with_name(f"{path.stem}.{tag}{path.suffix}")


def _set_precision(proto: onnx.ModelProto, precision: str) -> None:
    """Add metadata "precision"; drop tool annotations that are not JSON (the quantiser adds "onnx.infer")."""
    keep = []
    for p in proto.metadata_props:
        try:
            json.loads(p.value)
            keep.append((p.key, p.value))
        except json.JSONDecodeError:
            pass
    del proto.metadata_props[:]
    for key, value in keep:
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    for p in proto.metadata_props:
        if p.key == "precision":
            p.value = json.dumps(precision)
            return
    entry = proto.metadata_props.add()
    entry.key, entry.value = "precision", json.dumps(precision)


def topological_sort(graph: onnx.GraphProto) -> None:
    """Reorder ``graph.node`` so that every node comes after the producers of its inputs (the fp16 converter
    appends its input casts at the end)."""
    available = {i.name for i in graph.input} | {i.name for i in graph.initializer} | {""}
    pending, ordered = list(graph.node), []
    while pending:
        ready = [n for n in pending if all(i in available for i in n.input)]
        if not ready:
            raise ExportError("graph has a cycle or an input that nothing produces")
        for n in ready:
            ordered.append(n)
            available.update(n.output)
        ready_ids = {id(n) for n in ready}
        pending = [n for n in pending if id(n) not in ready_ids]
    copies = [onnx.NodeProto() for _ in ordered]
    for c, n in zip(copies, ordered):
        c.CopyFrom(n)
    del graph.node[:]
    graph.node.extend(copies)


def write_fp16(src: Path, dst: Path) -> Path:
    from onnxruntime.transformers.float16 import DEFAULT_OP_BLOCK_LIST, convert_float_to_float16

    proto = onnx.load(str(src))
    half = convert_float_to_float16(proto, keep_io_types=True, op_block_list=DEFAULT_OP_BLOCK_LIST + FP16_KEEP_FP32,
                                    node_block_list=activation_matmuls(proto))
    half.ir_version = proto.ir_version
    topological_sort(half.graph)
    del half.graph.value_info[:]          # stale fp32 annotations; the checker re-infers the types
    _set_precision(half, "fp16")
    validate_proto(half)
    onnx.save(half, str(dst))
    return dst


def activation_matmuls(proto: onnx.ModelProto) -> list[str]:
    """Names of the MatMul nodes with no weight (initializer) input: the in-graph image resampling (banded
    triangle-filter weights × image windows, values 0..255). Kept in float32 by both variants: fp16 would round
    the pixel sums to 1/8 of a grey level, int8 would quantise the filter weights and the images."""
    inits = {i.name for i in proto.graph.initializer}
    return [n.name for n in proto.graph.node if n.op_type == "MatMul" and not any(i in inits for i in n.input)]


def voxel_convs(proto: onnx.ModelProto) -> list[str]:
    """Names of the Conv nodes downstream of the voxel pooling (the ``ScatterND`` that writes the pooled sums into
    the trunk grid, or a ``ScatterElements`` that adds them): the 3D decoder's convolutions. Kept in float32 by the
    int8 variant: quantised, they changed the predicted occupancy of 29 % of the voxels of a trained base on the
    real frame (density error 0.68), against 0.06 % with them in float32 (docs/results.md#inference)."""
    consumers: dict[str, list] = {}
    for n in proto.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    seen, stack = set(), [o for n in proto.graph.node if n.op_type.startswith("Scatter") for o in n.output]
    names = []
    while stack:
        for n in consumers.get(stack.pop(), []):
            if id(n) in seen:
                continue
            seen.add(id(n))
            if n.op_type == "Conv":
                names.append(n.name)
            stack.extend(n.output)
    return names


INT8_OP_TYPES = ["Conv"]
# The int8 weight range (``int8_range``, occflownet.choices.INT8_RANGES): "reduced" (default) quantises weights to
# 7 bits: onnxruntime's u8s8 kernels on x86 CPUs without VNNI (AVX2 only) sum pairs of u8·s8 products in int16
# (vpmaddubsw), which saturates with 8-bit weights, so a "full"-range graph is only exact on CPUs with VNNI or AMX
# (one instruction multiplies and accumulates in int32). "full" keeps the 8th bit (half the rounding step of the
# weights) for such CPUs; docs/results.md#inference measures both.


def calibration_frames(folder: str | Path, cfg: ModelConfig, count: int) -> list[dict]:
    """``count`` batch-1 feeds made from one real frame as the inference paths decode it (JPEGs at reduced scale for
    ``cfg.input_size``): brightness/contrast varied (×0.6 … ×1.3 around mid-grey) and the rig turned about ego z,
    so the activation ranges cover other lighting and other voxels than the frame itself."""
    from occflownet.contract import load_calibration
    from occflownet.geometry import rotation_z
    from occflownet.predict import load_frame

    folder = Path(folder)
    frame = load_frame(folder, tuple(cfg.input_size))
    inputs = frame.inputs(load_calibration(folder / "calib.json"))
    feeds = []
    for i in range(count):
        gain = (0.6, 1.3, 0.85, 1.1, 0.75, 1.2)[i % 6]
        images = np.clip((inputs.images.astype(np.float32) - 128.0) * gain + 128.0 + 8.0 * (i % 3 - 1), 0, 255)
        turn = rotation_z(np.radians(-60.0 + 120.0 * i / max(1, count - 1))).astype(np.float32)
        feeds.append(ModelInputs(images.astype(np.uint8), inputs.intrinsics, turn @ inputs.cam2ego).feeds())
    return feeds


class _CalibrationReader:
    """onnxruntime CalibrationDataReader: ``count`` batch-1 feeds from the real-looking ``frame``
    (:func:`calibration_frames`), else synthetic samples (random images, default and turned rigs)."""

    def __init__(self, cfg: ModelConfig, count: int, frame: str | Path | None = None):
        self.samples = []
        if frame is not None:
            self.samples = calibration_frames(frame, cfg, count)
        for s in default_parity_samples(cfg, [], seed=11) if frame is None else []:
            self.samples += [one.feeds() for one in s.inputs.split()]
        self.samples = self.samples[:count]
        self._it = iter(self.samples)

    def get_next(self):
        return next(self._it, None)

    def rewind(self):
        self._it = iter(self.samples)


def float_in_int8(proto: onnx.ModelProto) -> list[str]:
    """The nodes of a quantisable type that the int8 variant leaves in float32."""
    return activation_matmuls(proto) + voxel_convs(proto)


def write_int8(src: Path, dst: Path, cfg: ModelConfig, calibration_samples: int = 6,
               frame: str | Path | None = None, int8_range: str = ExportConfig.int8_range,
               keep_float: list[str] | None = None, op_types: list[str] | None = None) -> Path:
    """The int8 QDQ variant of ``src`` (see the module docstring), calibrated on ``frame`` (a real frame folder)
    when given, else on synthetic samples; weights in ``int8_range`` (:data:`INT8_OP_TYPES` note). ``keep_float``
    (node names) and ``op_types`` replace :func:`float_in_int8` and :data:`INT8_OP_TYPES` (for measuring other
    choices, ``benchmarks/studies/int8_sensitivity.py``)."""
    if int8_range not in INT8_RANGES:
        raise ValueError(f"int8_range must be one of {INT8_RANGES}, got {int8_range!r}")
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    source = onnx.load(str(src))
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)   # the quantiser logs a "consider pre-processing" advice on the root logger
    try:
        quantize_static(str(src), str(dst), _CalibrationReader(cfg, calibration_samples, frame),
                        quant_format=QuantFormat.QDQ,
                        op_types_to_quantize=INT8_OP_TYPES if op_types is None else op_types,
                        nodes_to_exclude=float_in_int8(source) if keep_float is None else keep_float,
                        reduce_range=int8_range == "reduced",
                        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax)
    finally:
        root.setLevel(level)
    proto = onnx.load(str(dst))
    proto.ir_version = min(proto.ir_version, source.ir_version)
    _set_precision(proto, "int8")
    validate_proto(proto)
    onnx.save(proto, str(dst))
    return dst


def write_variants(fp32_path: str | Path, cfg: ModelConfig, fp16: bool = False, int8: bool = False,
                   frame: str | Path | None = None, int8_range: str = ExportConfig.int8_range) -> list[str]:
    """Write the requested variants beside ``fp32_path``; returns one report line per variant."""
    fp32_path = Path(fp32_path)
    sample = inference_frame_sample(frame, cfg) if frame else default_parity_samples(cfg, [], seed=5)[0]
    reference = OnnxPredictor.open(fp32_path)(sample.inputs)
    lines = []
    todo = [("fp16", write_fp16, ())] if fp16 else []
    todo += [("int8", write_int8, (cfg, 6, frame, int8_range))] if int8 else []
    for tag, writer, extra in todo:
        dst = _with_suffix(fp32_path, tag)
        try:
            writer(fp32_path, dst, *extra)
            out = OnnxPredictor.open(dst)(sample.inputs)
        except ExportError:
            dst.unlink(missing_ok=True)
            raise
        except Exception as exc:
            dst.unlink(missing_ok=True)
            raise ExportError(f"{tag} variant failed: {type(exc).__name__}: {exc}") from exc
        a = agreement(reference[0], reference[1], out[0], out[1])
        occupied = float(np.mean(reference[0] != FREE))
        lines.append(f"wrote {dst} ({dst.stat().st_size / 1e6:.1f} MB): vs fp32 on {sample.name}: occupancy equal "
                     f"{100 * a['occupancy_equal_fraction']:.3f}% of voxels (fp32 occupied "
                     f"{100 * occupied:.1f}%), density max abs diff {a['density_max_abs_diff']:.2e}")
    return lines
